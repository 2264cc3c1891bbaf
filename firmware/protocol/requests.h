// Request validation: pin capabilities and the CONFIG / TICK rules of docs/protocol.md.
// A request is validated whole before anything is applied; the first problem found is returned
// as (error code, detail) and nothing changes. Check order (shared with the Python codec):
//   CONFIG: body length; every pin (range, reserved, listed twice); every mode (known,
//           capability); the Timer1 conflict; every safe value.
//   TICK:   body length (< 6); every dout bit; every rmask bit; then each write in wire order
//           (pin mode, truncation, value). (NOT_CONFIGURED is checked first, by the engine.)
#ifndef HILSWARM_PROTOCOL_REQUESTS_H
#define HILSWARM_PROTOCOL_REQUESTS_H

#include <stdint.h>

#include "wire.h"

namespace hilswarm {

// One pin's configuration: mode and the value driven on watchdog trip / e-stop (wire units).
struct PinConfig {
  uint8_t mode;
  uint16_t safe;
};

// Outcome of a check: code 0 = valid, else an ERROR code and its detail byte.
struct RequestError {
  uint8_t code;
  uint8_t detail;
  bool ok() const { return code == 0; }
};

// Capability bits of `pin` on an ATmega328P board (Uno, Duemilanove, Fio); 0 for pin >= 20.
uint8_t pin_capabilities(uint8_t pin);

// True if `mode` is a known mode the capabilities `caps` allow (UNUSED needs none).
bool mode_allowed(uint8_t mode, uint8_t caps);

// True if `value` is a legal safe value for `mode` (inputs: any value, it is ignored).
bool safe_value_ok(uint8_t mode, uint16_t value);

// True for DIGITAL_IN, DIGITAL_IN_PULLUP and ANALOG_IN.
bool is_input_mode(uint8_t mode);

// Validates a CONFIG body (2 + 4n bytes, or 3 + 4n with the broadcast id of protocol 2 last).
// On success fills `config` (kPinCount entries; unlisted pins UNUSED), `*watchdog_ms`,
// `*n_entries` (pins listed in the request) and `*bcast_id` (0 when absent).
RequestError check_config(const uint8_t* body, uint8_t len, PinConfig* config,
                          uint16_t* watchdog_ms, uint8_t* n_entries, uint8_t* bcast_id);

// The pin sets a TICK is checked and applied against, as u24 masks stored a byte at a time
// (bit i of byte i / 8 = pin i; pins 20-23 never set). Derived from the configuration once per
// CONFIG so that a TICK costs a few byte operations instead of a walk over every pin.
struct PinSets {
  uint8_t dout[3];   // DIGITAL_OUT pins
  uint8_t input[3];  // DIGITAL_IN, DIGITAL_IN_PULLUP and ANALOG_IN pins
  uint8_t wide[3];   // PWM and SERVO pins (written by (pin, value) pairs)
  uint8_t servo[3];  // SERVO pins (u16 values)
};

// The pin sets of `config` (kPinCount entries).
PinSets pin_sets(const PinConfig* config);

// Bit of pin `pin` inside its byte of a u24 pin mask: 1 << (pin % 8), from a table (a variable
// shift is a loop on the AVR).
inline uint8_t pin_bit(uint8_t pin) {
  static const uint8_t kBits[8] = {0x01, 0x02, 0x04, 0x08, 0x10, 0x20, 0x40, 0x80};
  return kBits[pin & 7U];
}

// Validates a TICK body against the current configuration (kPinCount entries).
RequestError check_tick(const uint8_t* body, uint8_t len, const PinConfig* config);
// The same, with the configuration's pin sets already derived (the firmware's hot path).
RequestError check_tick(const uint8_t* body, uint8_t len, const PinConfig* config,
                        const PinSets& sets);

// Where board `id`'s section is in a BCAST body (sections id:u8 hdr:u8 data...): the offset of
// its data, with its header in `*hdr`; kNoSection if no section has that id, kBadBroadcast if
// the body is not a whole number of well-formed sections (checked to the end).
const int16_t kNoSection = -1;
const int16_t kBadBroadcast = -2;
int16_t find_section(const uint8_t* body, uint8_t len, uint8_t id, uint8_t* hdr);

// Little-endian readers.
inline uint16_t read_u16(const uint8_t* p) {
  return static_cast<uint16_t>(p[0] | (static_cast<uint16_t>(p[1]) << 8));
}
inline uint32_t read_u24(const uint8_t* p) {
  return static_cast<uint32_t>(p[0]) | (static_cast<uint32_t>(p[1]) << 8) |
         (static_cast<uint32_t>(p[2]) << 16);
}

// Size of the TICK body header (dout:u24 rmask:u24).
const uint8_t kTickHeader = 6;

}  // namespace hilswarm

#endif  // HILSWARM_PROTOCOL_REQUESTS_H
