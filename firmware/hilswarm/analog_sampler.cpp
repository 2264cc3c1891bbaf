#include "analog_sampler.h"

#include <Arduino.h>
#include <avr/interrupt.h>
#include <avr/io.h>
#include <util/atomic.h>

#include "wire.h"

namespace hilswarm {
namespace analog {

namespace {

const uint8_t kChannels = 6;  // A0-A5 = ADC0-ADC5
const uint8_t kNone = 0xFF;
const uint8_t kChannelBit[kChannels] = {0x01, 0x02, 0x04, 0x08, 0x10, 0x20};
// Longest wait for the first conversion of a pin just added [us]: a round of six conversions
// of <= 113 us plus margin (latest() restarts a stopped ADC first, so this is never reached).
const uint16_t kFirstSampleTimeoutUs = 2000;

volatile uint16_t samples[kChannels];
volatile uint8_t fresh_mask = 0;      // bit c: samples[c] is a conversion made since c was added
volatile uint8_t discard_mask = 0;    // bit c: drop the conversion under way (membership changed)
volatile uint8_t converting = kNone;  // channel of the conversion under way (kNone: ADC idle)
uint8_t sampled_mask = 0;             // bit c: pin 14 + c is sampled (changed with interrupts off)
// next_channel[c]: the sampled channel converted after channel c (round-robin; c itself when it
// is the only one; kNone when no channel is sampled). Rebuilt whenever sampled_mask changes, so
// the interrupt does one lookup.
uint8_t next_channel[kChannels] = {kNone, kNone, kNone, kNone, kNone, kNone};

// Starts converting `channel` (interrupts disabled). AVCC reference, as analogRead() with the
// default analogReference(); the prescaler bits stay as the Arduino core's init() set them.
inline void start(uint8_t channel) {
  converting = channel;
  ADMUX = static_cast<uint8_t>(_BV(REFS0) | channel);
  ADCSRA = static_cast<uint8_t>(_BV(ADEN) | _BV(ADSC) | _BV(ADIE) |
                                (ADCSRA & (_BV(ADPS2) | _BV(ADPS1) | _BV(ADPS0))));
}

void rebuild_next_channel() {
  for (uint8_t c = 0; c < kChannels; ++c) {
    uint8_t next = kNone;
    for (uint8_t step = 1; step <= kChannels; ++step) {
      const uint8_t candidate = static_cast<uint8_t>((c + step) % kChannels);
      if (sampled_mask & kChannelBit[candidate]) {
        next = candidate;
        break;
      }
    }
    next_channel[c] = next;
  }
}

}  // namespace

void set_sampled(uint8_t pin, bool sampled) {
  if (pin < wire::kAnalogPinBase || pin >= wire::kAnalogPinBase + kChannels) return;
  const uint8_t channel = static_cast<uint8_t>(pin - wire::kAnalogPinBase);
  const uint8_t bit = kChannelBit[channel];
  ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
    if (sampled == ((sampled_mask & bit) != 0)) return;
    fresh_mask &= static_cast<uint8_t>(~bit);
    // A conversion of this channel under way held its input under the old membership.
    if (converting == channel) discard_mask |= bit;
    if (sampled) {
      sampled_mask |= bit;
    } else {
      sampled_mask &= static_cast<uint8_t>(~bit);
    }
    rebuild_next_channel();
    if (sampled && converting == kNone) start(channel);
  }
}

uint16_t latest(uint8_t pin) {
  if (pin < wire::kAnalogPinBase || pin >= wire::kAnalogPinBase + kChannels) return 0;
  const uint8_t channel = static_cast<uint8_t>(pin - wire::kAnalogPinBase);
  const uint8_t bit = kChannelBit[channel];
  if (!(sampled_mask & bit)) return 0;
  if (!(fresh_mask & bit)) {  // only right after the pin became ANALOG_IN
    const uint16_t start_us = static_cast<uint16_t>(micros());
    while (!(fresh_mask & bit) &&
           static_cast<uint16_t>(static_cast<uint16_t>(micros()) - start_us) <
               kFirstSampleTimeoutUs) {
      ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
        if (converting == kNone) start(channel);  // never expected: the round-robin stopped
      }
    }
  }
  uint16_t value;
  ATOMIC_BLOCK(ATOMIC_RESTORESTATE) { value = samples[channel]; }
  return value;
}

}  // namespace analog
}  // namespace hilswarm

// Conversion complete: keep the result (read before ADMUX changes), start the next channel.
ISR(ADC_vect) {
  using namespace hilswarm::analog;
  const uint16_t value = ADC;
  const uint8_t channel = converting;
  const uint8_t bit = kChannelBit[channel];
  if (discard_mask & bit) {
    discard_mask &= static_cast<uint8_t>(~bit);
  } else {
    samples[channel] = value;
    fresh_mask |= bit;
  }
  const uint8_t next = next_channel[channel];
  if (next == kNone) {
    converting = kNone;
  } else {
    start(next);
  }
}
