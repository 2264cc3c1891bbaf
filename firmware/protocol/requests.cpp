#include "requests.h"

namespace hilswarm {

namespace {

const RequestError kOk = {0, 0};

RequestError fail(uint8_t code, uint8_t detail) {
  RequestError e = {code, detail};
  return e;
}

uint8_t mode_capability(uint8_t mode) {
  switch (mode) {
    case wire::kModeDigitalIn:
    case wire::kModeDigitalInPullup:
      return wire::kCapDigitalIn;
    case wire::kModeDigitalOut:
      return wire::kCapDigitalOut;
    case wire::kModePwm:
      return wire::kCapPwm;
    case wire::kModeServo:
      return wire::kCapServo;
    case wire::kModeAnalogIn:
      return wire::kCapAnalogIn;
    default:
      return 0;
  }
}

}  // namespace

uint8_t pin_capabilities(uint8_t pin) {
  if (pin >= wire::kPinCount) return 0;
  if (pin <= 1) return wire::kCapReserved;  // serial link
  if (pin >= wire::kAnalogPinBase) {
    return wire::kCapAnalogIn | wire::kCapDigitalIn | wire::kCapDigitalOut;
  }
  uint8_t caps = wire::kCapDigitalIn | wire::kCapDigitalOut;
  if (pin == 3 || pin == 5 || pin == 6 || pin == 9 || pin == 10 || pin == 11) {
    caps |= wire::kCapPwm;
  }
  if (pin == wire::kServoPinA || pin == wire::kServoPinB) caps |= wire::kCapServo;
  return caps;
}

bool mode_allowed(uint8_t mode, uint8_t caps) {
  if (mode >= wire::kModeCount) return false;
  const uint8_t need = mode_capability(mode);
  return need == 0 || (caps & need) != 0;
}

bool safe_value_ok(uint8_t mode, uint16_t value) {
  switch (mode) {
    case wire::kModeDigitalOut:
      return value <= 1;
    case wire::kModePwm:
      return value <= wire::kPwmMax;
    case wire::kModeServo:
      return value >= wire::kServoMinUs && value <= wire::kServoMaxUs;
    default:
      return true;  // inputs and UNUSED: the safe value is ignored
  }
}

bool is_input_mode(uint8_t mode) {
  return mode == wire::kModeDigitalIn || mode == wire::kModeDigitalInPullup ||
         mode == wire::kModeAnalogIn;
}

RequestError check_config(const uint8_t* body, uint8_t len, PinConfig* config,
                          uint16_t* watchdog_ms, uint8_t* n_entries, uint8_t* bcast_id) {
  if (len < 2 || (len - 2) % 4 > 1) return fail(wire::kErrBadLength, wire::kConfig);
  const uint8_t n = static_cast<uint8_t>((len - 2) / 4);
  const uint8_t* entries = body + 2;

  uint32_t seen = 0;
  for (uint8_t i = 0; i < n; ++i) {
    const uint8_t pin = entries[4 * i];
    if (pin >= wire::kPinCount || (pin_capabilities(pin) & wire::kCapReserved) ||
        (seen & (1UL << pin))) {
      return fail(wire::kErrBadPin, pin);
    }
    seen |= 1UL << pin;
  }
  uint8_t servo_a = 0, servo_b = 0, pwm_a = 0, pwm_b = 0;
  for (uint8_t i = 0; i < n; ++i) {
    const uint8_t pin = entries[4 * i];
    const uint8_t mode = entries[4 * i + 1];
    if (!mode_allowed(mode, pin_capabilities(pin))) return fail(wire::kErrBadMode, pin);
    if (pin == wire::kServoPinA) {
      servo_a = mode == wire::kModeServo;
      pwm_a = mode == wire::kModePwm;
    } else if (pin == wire::kServoPinB) {
      servo_b = mode == wire::kModeServo;
      pwm_b = mode == wire::kModePwm;
    }
  }
  // Timer1 makes the servo pulses: a servo on one of 9/10 takes PWM away from the other.
  if (servo_a && pwm_b) return fail(wire::kErrPinConflict, wire::kServoPinB);
  if (servo_b && pwm_a) return fail(wire::kErrPinConflict, wire::kServoPinA);
  for (uint8_t i = 0; i < n; ++i) {
    const uint8_t* e = entries + 4 * i;
    if (!safe_value_ok(e[1], read_u16(e + 2))) return fail(wire::kErrBadValue, e[0]);
  }

  for (uint8_t pin = 0; pin < wire::kPinCount; ++pin) {
    config[pin].mode = wire::kModeUnused;
    config[pin].safe = 0;
  }
  for (uint8_t i = 0; i < n; ++i) {
    const uint8_t* e = entries + 4 * i;
    config[e[0]].mode = e[1];
    config[e[0]].safe = read_u16(e + 2);
  }
  *watchdog_ms = read_u16(body);
  *n_entries = n;
  *bcast_id = (len - 2) % 4 == 1 ? body[len - 1] : 0;
  return kOk;
}

int16_t find_section(const uint8_t* body, uint8_t len, uint8_t id, uint8_t* hdr) {
  int16_t found = kNoSection;
  uint8_t i = 0;
  while (i < len) {
    if (static_cast<uint16_t>(i) + 2 > len || (body[i + 1] & wire::kBcastReservedFlag)) {
      return kBadBroadcast;
    }
    const uint16_t end = static_cast<uint16_t>(i + 2 + (body[i + 1] & wire::kBcastLengthMask));
    if (end > len) return kBadBroadcast;
    if (body[i] == id && found == kNoSection) {
      found = static_cast<int16_t>(i + 2);
      *hdr = body[i + 1];
    }
    i = static_cast<uint8_t>(end);
  }
  return found;
}

PinSets pin_sets(const PinConfig* config) {
  PinSets sets = {{0, 0, 0}, {0, 0, 0}, {0, 0, 0}, {0, 0, 0}};
  for (uint8_t pin = 0; pin < wire::kPinCount; ++pin) {
    const uint8_t mode = config[pin].mode;
    const uint8_t bit = pin_bit(pin);
    if (mode == wire::kModeDigitalOut) sets.dout[pin / 8] |= bit;
    if (is_input_mode(mode)) sets.input[pin / 8] |= bit;
    if (mode == wire::kModePwm || mode == wire::kModeServo) sets.wide[pin / 8] |= bit;
    if (mode == wire::kModeServo) sets.servo[pin / 8] |= bit;
  }
  return sets;
}

namespace {

// First pin of `mask` (u24, a byte at a time) that is not in `allowed`; kPinMaskBits if none.
// The masks are compared a byte at a time; only a faulty request walks the bits.
uint8_t first_pin_outside(const uint8_t* mask, const uint8_t* allowed) {
  for (uint8_t byte = 0; byte < 3; ++byte) {
    uint8_t bad = static_cast<uint8_t>(mask[byte] & ~allowed[byte]);
    if (bad == 0) continue;
    uint8_t pin = static_cast<uint8_t>(byte * 8);
    for (; !(bad & 1U); bad = static_cast<uint8_t>(bad >> 1)) ++pin;
    return pin;
  }
  return wire::kPinMaskBits;
}

}  // namespace

RequestError check_tick(const uint8_t* body, uint8_t len, const PinConfig* config) {
  return check_tick(body, len, config, pin_sets(config));
}

RequestError check_tick(const uint8_t* body, uint8_t len, const PinConfig* /*config*/,
                        const PinSets& sets) {
  if (len < kTickHeader) return fail(wire::kErrBadLength, wire::kTick);
  // Every dout bit, then every rmask bit (the first offending pin in ascending order).
  uint8_t pin = first_pin_outside(body, sets.dout);
  if (pin != wire::kPinMaskBits) return fail(wire::kErrBadPin, pin);
  pin = first_pin_outside(body + 3, sets.input);
  if (pin != wire::kPinMaskBits) return fail(wire::kErrBadPin, pin);
  uint8_t i = kTickHeader;
  uint8_t written[3] = {0, 0, 0};  // pins written so far (one write per pin)
  while (i < len) {
    pin = body[i];
    if (pin >= wire::kPinMaskBits) return fail(wire::kErrBadPin, pin);
    const uint8_t byte = static_cast<uint8_t>(pin / 8);
    const uint8_t bit = pin_bit(pin);
    if (!(sets.wide[byte] & bit)) return fail(wire::kErrBadPin, pin);  // not PWM or SERVO
    if (written[byte] & bit) return fail(wire::kErrBadPin, pin);
    written[byte] |= bit;
    if (sets.servo[byte] & bit) {
      if (static_cast<uint16_t>(i) + 3 > len) return fail(wire::kErrBadLength, wire::kTick);
      const uint16_t us = read_u16(body + i + 1);
      if (us < wire::kServoMinUs || us > wire::kServoMaxUs) return fail(wire::kErrBadValue, pin);
      i = static_cast<uint8_t>(i + 3);
    } else {
      if (static_cast<uint16_t>(i) + 2 > len) return fail(wire::kErrBadLength, wire::kTick);
      i = static_cast<uint8_t>(i + 2);
    }
  }
  return kOk;
}

}  // namespace hilswarm
