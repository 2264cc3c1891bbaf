// hal.h for ATmega328P Arduino boards: pin modes through the Arduino core (pinMode,
// digitalWrite), outputs straight to the port and timer registers, analog inputs sampled in the
// background by the ADC interrupt (analog_sampler), servo pulses through servo_timer1, the board
// id in EEPROM.
#include <Arduino.h>
#include <avr/eeprom.h>
#include <util/atomic.h>

#include "analog_sampler.h"
#include "firmware_config.h"
#include "hal.h"
#include "servo_timer1.h"
#include "wire.h"

namespace hilswarm {
namespace hal {

void set_pin_mode(uint8_t pin, uint8_t mode) {
  if (servo::attached(pin)) servo::detach(pin);
  analog::set_sampled(pin, mode == wire::kModeAnalogIn);
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

// analogWrite() for the six PWM pins of an ATmega328P, without its per-call pinMode() and pin
// table lookups (set_pin_mode made the pin an output): duty 0 and 255 drive the pin as a plain
// digital output with the timer disconnected, anything else connects the timer's compare output
// and sets the duty — exactly as analogWrite() does.
void write_pwm(uint8_t pin, uint8_t duty) {
  if (duty == 0 || duty == 255) {
    digitalWrite(pin, duty ? HIGH : LOW);  // disconnects the timer (turnOffPWM)
    return;
  }
  switch (pin) {
    case 3:
      TCCR2A |= _BV(COM2B1);
      OCR2B = duty;
      break;
    case 5:
      TCCR0A |= _BV(COM0B1);
      OCR0B = duty;
      break;
    case 6:
      TCCR0A |= _BV(COM0A1);
      OCR0A = duty;
      break;
    case 9:
      ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {  // 16-bit register write through TEMP
        TCCR1A |= _BV(COM1A1);
        OCR1A = duty;
      }
      break;
    case 10:
      ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
        TCCR1A |= _BV(COM1B1);
        OCR1B = duty;
      }
      break;
    case 11:
      TCCR2A |= _BV(COM2A1);
      OCR2A = duty;
      break;
    default:  // not a PWM pin: the engine never writes one (check_tick)
      break;
  }
}

void write_servo(uint8_t pin, uint16_t pulse_us) { servo::write_us(pin, pulse_us); }

uint8_t read_digital(uint8_t pin) { return digitalRead(pin) == HIGH ? 1 : 0; }

uint16_t read_analog(uint8_t pin) { return analog::latest(pin); }

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
