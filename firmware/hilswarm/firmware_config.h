// Firmware constants (board side). Wire-format constants live in ../protocol/wire.h.
#ifndef HILSWARM_FIRMWARE_CONFIG_H
#define HILSWARM_FIRMWARE_CONFIG_H

#include <avr/wdt.h>
#include <stdint.h>

#ifndef HILSWARM_BAUD
#define HILSWARM_BAUD 115200UL  // docs/protocol.md: 115200 8N1 (override: make BAUD=57600)
#endif

namespace hilswarm {
namespace config {

// Firmware version (reported by HELLO; separate from wire::kProtocolVersion).
const uint8_t kFirmwareMajor = 1;
const uint8_t kFirmwareMinor = 2;  // 1.2: protocol 2 (BCAST)

const uint32_t kBaud = HILSWARM_BAUD;

// Periodic work (link watchdog check) runs every kPeriodUs on a drift-free schedule
// (next += period). After a stall of more than kMaxLagPeriods periods the schedule restarts
// from now instead of running a burst of catch-up periods.
const uint32_t kPeriodUs = 1000;
const uint32_t kMaxLagPeriods = 10;

// Received bytes handled per loop() at most (16 bytes = 1.4 ms of a busy line at 115200 baud)
// before the periodic work gets its turn.
const uint8_t kMaxBytesPerLoop = 16;

// AVR hardware watchdog timeout (reset by loop()).
const uint8_t kHwWatchdogTimeout = WDTO_250MS;

// Board id in EEPROM: a magic word marks the id as set (fresh EEPROM reads 0xFF).
const uint16_t kEepromMagicAddress = 0;
const uint16_t kEepromIdAddress = 2;
const uint16_t kEepromMagic = 0x4853;  // "HS"

// Servo pulses: Timer1 fast PWM mode 14, TOP = ICR1, prescaler 8, 20 ms period.
const uint32_t kServoPeriodUs = 20000;
const uint8_t kTimer1Prescaler = 8;

}  // namespace config
}  // namespace hilswarm

#endif  // HILSWARM_FIRMWARE_CONFIG_H
