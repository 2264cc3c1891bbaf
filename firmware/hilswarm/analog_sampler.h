// Background sampling of the ANALOG_IN pins: the ADC converts them round-robin, one conversion
// after the other, driven by its conversion-complete interrupt, so a TICK reads the latest
// finished conversion instead of waiting ~104 us for a fresh one.
//
// Sample age: the ADC clock is F_CPU / 128 (16 MHz) or F_CPU / 64 (8 MHz) = 125 kHz, as the
// Arduino core sets it up, and a conversion takes 13 ADC clocks (104 us) plus up to one ADC
// clock and the interrupt's latency before the next one starts: T <= 113 us. With N pins
// sampled, every pin is converted again at least every N x T, and a conversion holds its input
// 1.5 ADC clocks after it starts, so the value latest() returns was taken at most
// N x T + 11.5 ADC clocks <= (N + 1) x 113 us before the call (N = 1: <= 226 us; all six
// analog pins: <= 791 us).
#ifndef HILSWARM_ANALOG_SAMPLER_H
#define HILSWARM_ANALOG_SAMPLER_H

#include <stdint.h>

namespace hilswarm {
namespace analog {

// Adds (sampled = true) or removes pin `pin` (14-19 = A0-A5; other pins are ignored) from the
// round-robin. A pin added now has no sample until its first conversion has finished.
void set_sampled(uint8_t pin, bool sampled);

// The latest finished conversion of pin `pin` (0-1023 ADC counts, AVCC reference). Waits for
// the first one if the pin was only just added (at most one round, see above); 0 for a pin
// that is not sampled.
uint16_t latest(uint8_t pin);

}  // namespace analog
}  // namespace hilswarm

#endif  // HILSWARM_ANALOG_SAMPLER_H
