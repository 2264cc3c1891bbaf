// Frame builder: assembles a reply payload (type, seq, body) and turns it into a wire frame
// COBS(payload || crc16_le(payload)) || 0x00. Fixed buffers, no allocation.
#ifndef HILSWARM_PROTOCOL_FRAME_BUILDER_H
#define HILSWARM_PROTOCOL_FRAME_BUILDER_H

#include <stddef.h>
#include <stdint.h>

#include "wire.h"

namespace hilswarm {

class FrameBuilder {
 public:
  // Starts a payload with its type and seq.
  void begin(uint8_t type, uint8_t seq);
  void put_u8(uint8_t v);
  void put_u16(uint16_t v);   // little-endian
  void put_u24(uint32_t v);   // little-endian, low 24 bits
  void put_u32(uint32_t v);   // little-endian

  // True if a put_*() did not fit into kMaxPayload bytes (the payload is then truncated).
  bool overflow() const { return overflow_; }
  const uint8_t* payload() const { return payload_; }
  uint8_t payload_length() const { return len_; }

  // Appends the CRC, COBS-encodes and adds the delimiter. Returns the wire frame (valid until
  // the next begin()) and its length in `*wire_len`.
  const uint8_t* finish(size_t* wire_len);

 private:
  uint8_t payload_[wire::kMaxFrame];        // payload + room for the CRC
  uint8_t wire_[wire::kMaxEncoded + 1];     // encoded frame + delimiter
  uint8_t len_ = 0;
  bool overflow_ = false;
};

}  // namespace hilswarm

#endif  // HILSWARM_PROTOCOL_FRAME_BUILDER_H
