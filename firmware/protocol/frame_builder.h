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
  void begin(uint8_t type, uint8_t seq) {
    payload_[0] = type;
    payload_[1] = seq;
    len_ = 2;
    overflow_ = false;
  }
  // Inline: they run for every reply byte.
  void put_u8(uint8_t v) {
    if (len_ < wire::kMaxPayload) {
      payload_[len_++] = v;
    } else {
      overflow_ = true;
    }
  }
  void put_u16(uint16_t v) {  // little-endian
    put_u8(static_cast<uint8_t>(v));
    put_u8(static_cast<uint8_t>(v >> 8));
  }
  void put_u24(uint32_t v);   // little-endian, low 24 bits
  void put_u32(uint32_t v) {  // little-endian
    put_u16(static_cast<uint16_t>(v));
    put_u16(static_cast<uint16_t>(v >> 16));
  }

  // Overwrites the 4 payload bytes at `offset` (little-endian u32) of a payload already built
  // (before finish(); offset + 4 <= payload_length()).
  void patch_u32(uint8_t offset, uint32_t v) {
    payload_[offset] = static_cast<uint8_t>(v);
    payload_[offset + 1] = static_cast<uint8_t>(v >> 8);
    payload_[offset + 2] = static_cast<uint8_t>(v >> 16);
    payload_[offset + 3] = static_cast<uint8_t>(v >> 24);
  }

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
