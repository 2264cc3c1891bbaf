// Byte-at-a-time frame parser: COBS-decodes, length-checks and CRC-checks incoming frames.
// Never blocks, never allocates; garbage is discarded up to the next 0x00 (resynchronisation).
#ifndef HILSWARM_PROTOCOL_FRAME_PARSER_H
#define HILSWARM_PROTOCOL_FRAME_PARSER_H

#include <stdint.h>

#include "cobs.h"
#include "crc16.h"
#include "wire.h"

namespace hilswarm {

class FrameParser {
 public:
  enum Result : uint8_t {
    kNone = 0,      // byte consumed, no frame finished (also: an empty frame = idle line)
    kFrame,         // a CRC-valid frame: payload() / payload_length()
    kTooLong,       // decoded frame longer than payload + CRC limit (answer FRAME_TOO_LONG)
    kTooShort,      // fewer than 4 decoded bytes (dropped silently, counted)
    kBadCobs,       // last COBS block truncated (dropped silently, counted)
    kBadCrc,        // CRC mismatch (dropped silently, counted)
  };

  FrameParser() : decoder_(buf_, wire::kMaxFrame) {}
  // Not copyable: the decoder points into this object's own buffer.
  FrameParser(const FrameParser&) = delete;
  FrameParser& operator=(const FrameParser&) = delete;

  // Forgets any partial frame (the next byte starts a new one).
  void reset() {
    decoder_.reset();
    crc_ = kCrc16Init;
    crc_len_ = 0;
  }

  // Consumes one received byte. Returns kFrame when `byte` completed a valid frame; the payload
  // stays valid until the next call to feed().
  Result feed(uint8_t byte);

  // Type, seq and body of the last valid frame (CRC removed).
  const uint8_t* payload() const { return buf_; }
  uint8_t payload_length() const { return payload_len_; }

  // After feed() returned kNone for a data byte: true if the bytes so far are a whole, CRC-valid
  // frame, i.e. a delimiter next would make feed() return kFrame with payload() holding
  // candidate_length() bytes. Lets the firmware prepare its answer in the byte time before the
  // delimiter arrives (a wrong guess costs idle time only: one in 65536 for a random byte).
  bool could_end_here() const {
    const uint8_t n = decoder_.length();
    if (n < wire::kMinFrame || decoder_.overflow() || !decoder_.complete()) return false;
    return crc_len_ + wire::kCrcSize == n && crc_ == static_cast<uint16_t>(
        buf_[n - 2] | (static_cast<uint16_t>(buf_[n - 1]) << 8));
  }
  // Bytes decoded so far in the current frame (type, seq, body, CRC as they arrive).
  uint8_t decoded_length() const { return decoder_.length(); }
  // Payload length (type, seq, body) of the frame could_end_here() found.
  uint8_t candidate_length() const {
    return static_cast<uint8_t>(decoder_.length() - wire::kCrcSize);
  }

 private:
  uint8_t buf_[wire::kMaxFrame];
  CobsDecoder decoder_;
  uint8_t payload_len_ = 0;
  // CRC of buf_[0, crc_len_), folded in while the frame arrives (the CPU is idle between bytes)
  // so the delimiter costs no CRC pass. The last two decoded bytes are held back: they may be
  // the frame's own CRC.
  uint16_t crc_ = kCrc16Init;
  uint8_t crc_len_ = 0;
};

}  // namespace hilswarm

#endif  // HILSWARM_PROTOCOL_FRAME_PARSER_H
