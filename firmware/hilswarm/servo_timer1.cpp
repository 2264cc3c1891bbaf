#include "servo_timer1.h"

#include <avr/io.h>
#include <util/atomic.h>

#include "firmware_config.h"

namespace hilswarm {
namespace servo {

namespace {

const uint32_t kTicksPerSecond = F_CPU / config::kTimer1Prescaler;
const uint16_t kTop = static_cast<uint16_t>(kTicksPerSecond / (1000000UL / config::kServoPeriodUs) - 1);
const uint16_t kNeutralUs = 1500;

uint8_t attached_mask = 0;  // bit 0 = pin 9, bit 1 = pin 10

uint8_t bit_of(uint8_t pin) { return pin == 9 ? 1 : (pin == 10 ? 2 : 0); }

// Timer ticks for a pulse: fast PWM holds the pin high for OCR1x + 1 ticks.
// Whole timer ticks per microsecond (2 at 16 MHz, 1 at 8 MHz): a multiply instead of a 32-bit
// division, which costs ~36 us on the AVR in every TICK that moves a servo.
static_assert(kTicksPerSecond % 1000000UL == 0, "Timer1 ticks per microsecond must be whole");
uint16_t compare_value(uint16_t pulse_us) {
  const uint32_t ticks = static_cast<uint32_t>(pulse_us) * (kTicksPerSecond / 1000000UL);
  return static_cast<uint16_t>(ticks - 1);
}

void start_mode14() {
  ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
    TCCR1B = 0;  // stop
    TCCR1A = _BV(WGM11);
    TCNT1 = 0;
    ICR1 = kTop;
    TCCR1B = _BV(WGM13) | _BV(WGM12) | _BV(CS11);  // mode 14, prescaler 8
  }
}

void restore_arduino_timer1() {
  ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
    TCCR1B = 0;
    TCCR1A = _BV(WGM10);  // 8-bit phase-correct PWM, as wiring.c's init()
    TCNT1 = 0;
    TCCR1B = _BV(CS11) | _BV(CS10);  // prescaler 64
  }
}

}  // namespace

bool is_servo_pin(uint8_t pin) { return bit_of(pin) != 0; }

bool attached(uint8_t pin) { return (attached_mask & bit_of(pin)) != 0; }

void attach(uint8_t pin) {
  const uint8_t bit = bit_of(pin);
  if (bit == 0 || (attached_mask & bit)) return;
  if (attached_mask == 0) start_mode14();
  attached_mask |= bit;
  write_us(pin, kNeutralUs);
  if (pin == 9) {
    DDRB |= _BV(DDB1);
    TCCR1A |= _BV(COM1A1);
  } else {
    DDRB |= _BV(DDB2);
    TCCR1A |= _BV(COM1B1);
  }
}

void detach(uint8_t pin) {
  const uint8_t bit = bit_of(pin);
  if (bit == 0 || !(attached_mask & bit)) return;
  TCCR1A &= static_cast<uint8_t>(pin == 9 ? ~_BV(COM1A1) : ~_BV(COM1B1));
  attached_mask &= static_cast<uint8_t>(~bit);
  if (attached_mask == 0) restore_arduino_timer1();
}

void write_us(uint8_t pin, uint16_t pulse_us) {
  const uint16_t value = compare_value(pulse_us);
  ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {  // 16-bit register write through TEMP
    if (pin == 9) {
      OCR1A = value;
    } else if (pin == 10) {
      OCR1B = value;
    }
  }
}

}  // namespace servo
}  // namespace hilswarm
