// CRC-16/CCITT-FALSE: polynomial 0x1021, init 0xFFFF, no reflection, no final xor.
// Check value of ASCII "123456789" = 0x29B1.
#ifndef HILSWARM_PROTOCOL_CRC16_H
#define HILSWARM_PROTOCOL_CRC16_H

#include <stddef.h>
#include <stdint.h>

namespace hilswarm {

const uint16_t kCrc16Init = 0xFFFF;

// Folds one byte into a running CRC (start from kCrc16Init).
uint16_t crc16_update(uint16_t crc, uint8_t byte);

// CRC of `len` bytes at `data`.
uint16_t crc16(const uint8_t* data, size_t len);

}  // namespace hilswarm

#endif  // HILSWARM_PROTOCOL_CRC16_H
