#include "frame_builder.h"

#include "cobs.h"
#include "crc16.h"

namespace hilswarm {

void FrameBuilder::begin(uint8_t type, uint8_t seq) {
  len_ = 0;
  overflow_ = false;
  put_u8(type);
  put_u8(seq);
}

void FrameBuilder::put_u8(uint8_t v) {
  if (len_ < wire::kMaxPayload) {
    payload_[len_++] = v;
  } else {
    overflow_ = true;
  }
}

void FrameBuilder::put_u16(uint16_t v) {
  put_u8(static_cast<uint8_t>(v));
  put_u8(static_cast<uint8_t>(v >> 8));
}

void FrameBuilder::put_u24(uint32_t v) {
  put_u16(static_cast<uint16_t>(v));
  put_u8(static_cast<uint8_t>(v >> 16));
}

void FrameBuilder::put_u32(uint32_t v) {
  put_u16(static_cast<uint16_t>(v));
  put_u16(static_cast<uint16_t>(v >> 16));
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
