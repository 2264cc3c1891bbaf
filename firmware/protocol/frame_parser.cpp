#include "frame_parser.h"

#include "crc16.h"

namespace hilswarm {

FrameParser::Result FrameParser::feed(uint8_t byte) {
  if (byte != wire::kDelimiter) {
    decoder_.feed(byte);
    while (static_cast<uint8_t>(crc_len_ + wire::kCrcSize) < decoder_.length()) {
      crc_ = crc16_update(crc_, buf_[crc_len_++]);
    }
    return kNone;
  }
  // Delimiter: judge the frame, then start the next one.
  Result result = kNone;
  if (!decoder_.started()) {
    result = kNone;  // consecutive delimiters: idle line, not a frame
  } else if (decoder_.overflow()) {
    result = kTooLong;
  } else if (!decoder_.complete()) {
    result = kBadCobs;
  } else if (decoder_.length() < wire::kMinFrame) {
    result = kTooShort;
  } else {
    const uint8_t n = static_cast<uint8_t>(decoder_.length() - wire::kCrcSize);
    const uint16_t got = static_cast<uint16_t>(buf_[n] | (buf_[n + 1] << 8));
    while (crc_len_ < n) crc_ = crc16_update(crc_, buf_[crc_len_++]);  // normally none left
    if (crc_ == got) {
      payload_len_ = n;
      result = kFrame;
    } else {
      result = kBadCrc;
    }
  }
  reset();
  return result;
}

}  // namespace hilswarm
