// Servo pulses on pins 9 (OC1A) and 10 (OC1B) from Timer1 in fast PWM mode 14 (TOP = ICR1,
// 20 ms period, prescaler 8: 0.5 µs resolution at 16 MHz, 1 µs at 8 MHz). No Servo library.
// While a servo is attached Timer1 cannot make Arduino's 8-bit PWM, so analogWrite on the other
// Timer1 pin is lost (the protocol forbids that combination: PIN_CONFLICT). When the last servo
// detaches Timer1 goes back to Arduino's default (8-bit phase-correct PWM, prescaler 64).
#ifndef HILSWARM_SERVO_TIMER1_H
#define HILSWARM_SERVO_TIMER1_H

#include <stdint.h>

namespace hilswarm {
namespace servo {

bool is_servo_pin(uint8_t pin);
bool attached(uint8_t pin);
// Connects the pin's compare output (pulse 1500 µs until written); starts mode 14 if needed.
void attach(uint8_t pin);
// Disconnects the pin's compare output; restores Arduino's Timer1 setup after the last one.
void detach(uint8_t pin);
// Pulse width [µs] of an attached servo pin (caller validated 500-2500 µs).
void write_us(uint8_t pin, uint16_t pulse_us);

}  // namespace servo
}  // namespace hilswarm

#endif  // HILSWARM_SERVO_TIMER1_H
