// A fake board behind hal.h for the host tests: records every output and checks that the
// engine only drives pins the way their current mode allows (violations are counted).
#ifndef HILSWARM_HOST_TEST_FAKE_HAL_H
#define HILSWARM_HOST_TEST_FAKE_HAL_H

#include <stdint.h>

#include <string>

namespace fake {

struct Board {
  uint8_t mode[20];          // as set through hal::set_pin_mode
  int digital_out[20];       // last level written (-1: never)
  int pwm[20];               // last duty written (-1: never)
  int servo[20];             // last pulse written [µs] (-1: never)
  uint8_t digital_in[20];    // what read_digital returns
  uint16_t analog_in[20];    // what read_analog returns
  uint16_t eeprom_id;
  bool eeprom_set;
  long writes;               // number of output writes
  long violations;
  std::string last_violation;
};

extern Board board;

// Back to power-on: every pin UNUSED, nothing written, blank EEPROM (keep_eeprom: keep the id).
void reset(bool keep_eeprom = false);

}  // namespace fake

#endif  // HILSWARM_HOST_TEST_FAKE_HAL_H
