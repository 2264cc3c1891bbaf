// CRC-16/CCITT-FALSE: polynomial 0x1021, init 0xFFFF, no reflection, no final xor.
// Check value of ASCII "123456789" = 0x29B1.
//
// Table driven: one lookup per byte. On the AVR the 512-byte table lives in flash (PROGMEM) and
// the update is inlined (~15 cycles a byte instead of ~50 for the shift form plus a call): it
// runs for every request byte as it arrives and for every reply byte before the reply can start.
#ifndef HILSWARM_PROTOCOL_CRC16_H
#define HILSWARM_PROTOCOL_CRC16_H

#include <stddef.h>
#include <stdint.h>

#ifdef __AVR__
#include <avr/pgmspace.h>
#define HILSWARM_CRC16_TABLE_ATTR PROGMEM
#define HILSWARM_CRC16_TABLE_READ(entry) pgm_read_word(entry)
#else
#define HILSWARM_CRC16_TABLE_ATTR
#define HILSWARM_CRC16_TABLE_READ(entry) (*(entry))
#endif

namespace hilswarm {

const uint16_t kCrc16Init = 0xFFFF;

// kCrc16Table[i] = CRC register after shifting the byte i through an all-zero register.
extern const uint16_t kCrc16Table[256] HILSWARM_CRC16_TABLE_ATTR;

// Folds one byte into a running CRC (start from kCrc16Init).
inline uint16_t crc16_update(uint16_t crc, uint8_t byte) {
  const uint8_t index = static_cast<uint8_t>((crc >> 8) ^ byte);
  return static_cast<uint16_t>((crc << 8) ^ HILSWARM_CRC16_TABLE_READ(&kCrc16Table[index]));
}

// CRC of `len` bytes at `data`.
uint16_t crc16(const uint8_t* data, size_t len);

}  // namespace hilswarm

#endif  // HILSWARM_PROTOCOL_CRC16_H
