// hal.h for ATmega328P Arduino boards: pins through the Arduino core (pinMode, digitalWrite,
// analogWrite, analogRead), servo pulses through servo_timer1, the board id in EEPROM.
#include <Arduino.h>
#include <avr/eeprom.h>

#include "firmware_config.h"
#include "hal.h"
#include "servo_timer1.h"
#include "wire.h"

namespace hilswarm {
namespace hal {

void set_pin_mode(uint8_t pin, uint8_t mode) {
  if (servo::attached(pin)) servo::detach(pin);
  // digitalWrite disconnects a PWM timer output (turnOffPWM) and drops the pull-up.
  digitalWrite(pin, LOW);
  switch (mode) {
    case wire::kModeDigitalInPullup:
      pinMode(pin, INPUT_PULLUP);
      break;
    case wire::kModeDigitalOut:
    case wire::kModePwm:
      pinMode(pin, OUTPUT);
      break;
    case wire::kModeServo:
      pinMode(pin, OUTPUT);
      servo::attach(pin);
      break;
    default:  // UNUSED, DIGITAL_IN, ANALOG_IN: high-impedance input
      pinMode(pin, INPUT);
      break;
  }
}

// Only called for DIGITAL_OUT pins, whose timer output set_pin_mode already disconnected: the
// port bit alone, without digitalWrite's PWM check (~1 us instead of ~4 us per pin).
void write_digital(uint8_t pin, uint8_t level) {
  volatile uint8_t* out = portOutputRegister(digitalPinToPort(pin));
  const uint8_t mask = digitalPinToBitMask(pin);
  const uint8_t sreg = SREG;
  cli();
  if (level) {
    *out |= mask;
  } else {
    *out = static_cast<uint8_t>(*out & ~mask);
  }
  SREG = sreg;
}

void write_pwm(uint8_t pin, uint8_t duty) { analogWrite(pin, duty); }

void write_servo(uint8_t pin, uint16_t pulse_us) { servo::write_us(pin, pulse_us); }

uint8_t read_digital(uint8_t pin) { return digitalRead(pin) == HIGH ? 1 : 0; }

uint16_t read_analog(uint8_t pin) { return static_cast<uint16_t>(analogRead(pin)); }

uint16_t load_board_id() {
  const uint16_t* magic = reinterpret_cast<const uint16_t*>(config::kEepromMagicAddress);
  const uint16_t* id = reinterpret_cast<const uint16_t*>(config::kEepromIdAddress);
  if (eeprom_read_word(magic) != config::kEepromMagic) return 0;
  return eeprom_read_word(id);
}

void store_board_id(uint16_t id) {
  eeprom_update_word(reinterpret_cast<uint16_t*>(config::kEepromIdAddress), id);
  eeprom_update_word(reinterpret_cast<uint16_t*>(config::kEepromMagicAddress),
                     config::kEepromMagic);
}

}  // namespace hal
}  // namespace hilswarm
