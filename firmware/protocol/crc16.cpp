#include "crc16.h"

namespace hilswarm {

// Byte-wise form of the bit-serial polynomial division (identical result for every crc/byte
// pair; checked exhaustively): a few shifts per byte instead of an 8-step loop, which matters on
// the 16 MHz AVR where this runs for every request and reply byte.
uint16_t crc16_update(uint16_t crc, uint8_t byte) {
  uint8_t x = static_cast<uint8_t>((crc >> 8) ^ byte);
  x = static_cast<uint8_t>(x ^ (x >> 4));
  return static_cast<uint16_t>((crc << 8) ^ (static_cast<uint16_t>(x) << 12) ^
                               (static_cast<uint16_t>(x) << 5) ^ x);
}

uint16_t crc16(const uint8_t* data, size_t len) {
  uint16_t crc = kCrc16Init;
  for (size_t i = 0; i < len; ++i) crc = crc16_update(crc, data[i]);
  return crc;
}

}  // namespace hilswarm
