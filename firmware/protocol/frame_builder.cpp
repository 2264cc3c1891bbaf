#include "frame_builder.h"

#include "cobs.h"
#include "crc16.h"

namespace hilswarm {

void FrameBuilder::put_u24(uint32_t v) {
  put_u16(static_cast<uint16_t>(v));
  put_u8(static_cast<uint8_t>(v >> 16));
}

const uint8_t* FrameBuilder::finish(size_t* wire_len) {
  const uint16_t crc = crc16(payload_, len_);
  payload_[len_] = static_cast<uint8_t>(crc);
  payload_[len_ + 1] = static_cast<uint8_t>(crc >> 8);
  size_t n = cobs_encode(payload_, static_cast<size_t>(len_) + wire::kCrcSize, wire_,
                         sizeof(wire_) - 1);
  wire_[n++] = wire::kDelimiter;
  *wire_len = n;
  return wire_;
}

}  // namespace hilswarm
