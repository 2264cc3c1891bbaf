// The board operations the protocol engine needs. Implemented for the AVR by
// firmware/hilswarm/board_io.cpp and for the host tests by firmware/host_test/fake_hal.cpp
// (link-time polymorphism: no virtual calls, no vtables in the AVR's RAM).
// Pins are Arduino numbers (0-19, A0 = 14); values are wire units.
#ifndef HILSWARM_PROTOCOL_HAL_H
#define HILSWARM_PROTOCOL_HAL_H

#include <stdint.h>

namespace hilswarm {
namespace hal {

// Puts `pin` into `mode` (wire::kMode*): UNUSED = high-impedance input. Leaving PWM disconnects
// the timer output; entering/leaving SERVO attaches/detaches the Timer1 pulse output.
void set_pin_mode(uint8_t pin, uint8_t mode);

void write_digital(uint8_t pin, uint8_t level);       // 0/1
void write_pwm(uint8_t pin, uint8_t duty);            // 0-255
void write_servo(uint8_t pin, uint16_t pulse_us);     // 500-2500 µs, validated by the caller
uint8_t read_digital(uint8_t pin);                    // 0/1
uint16_t read_analog(uint8_t pin);                    // 0-1023 ADC counts, pin 14-19

uint16_t load_board_id();                             // persistent id (EEPROM); 0 if never set
void store_board_id(uint16_t id);

}  // namespace hal
}  // namespace hilswarm

#endif  // HILSWARM_PROTOCOL_HAL_H
