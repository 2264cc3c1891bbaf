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
                          uint16_t* watchdog_ms, uint8_t* n_entries) {
  if (len < 2 || (len - 2) % 4 != 0) return fail(wire::kErrBadLength, wire::kConfig);
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
  return kOk;
}

RequestError check_tick(const uint8_t* body, uint8_t len, const PinConfig* config) {
  if (len < kTickHeader) return fail(wire::kErrBadLength, wire::kTick);
  // The u24 masks are walked a byte at a time, shifting the byte right one pin per step:
  // `1UL << pin` is a loop of `pin` steps on the AVR (no barrel shifter) and made this check
  // cost ~340 us per TICK.
  for (uint8_t pin = 0; pin < wire::kPinMaskBits; pin = static_cast<uint8_t>(pin + 8)) {
    uint8_t bits = body[pin / 8];
    for (uint8_t p = pin; bits != 0; ++p, bits = static_cast<uint8_t>(bits >> 1)) {
      if ((bits & 1U) && (p >= wire::kPinCount || config[p].mode != wire::kModeDigitalOut)) {
        return fail(wire::kErrBadPin, p);
      }
    }
  }
  for (uint8_t pin = 0; pin < wire::kPinMaskBits; pin = static_cast<uint8_t>(pin + 8)) {
    uint8_t bits = body[3 + pin / 8];
    for (uint8_t p = pin; bits != 0; ++p, bits = static_cast<uint8_t>(bits >> 1)) {
      if ((bits & 1U) && (p >= wire::kPinCount || !is_input_mode(config[p].mode))) {
        return fail(wire::kErrBadPin, p);
      }
    }
  }
  uint8_t i = kTickHeader;
  bool written[wire::kPinCount] = {};  // a flag per pin: no 32-bit variable shifts on the AVR
  while (i < len) {
    const uint8_t pin = body[i];
    const uint8_t mode = pin < wire::kPinCount ? config[pin].mode : wire::kModeUnused;
    if (mode != wire::kModePwm && mode != wire::kModeServo) return fail(wire::kErrBadPin, pin);
    if (written[pin]) return fail(wire::kErrBadPin, pin);  // one write per pin
    written[pin] = true;
    const uint8_t width = mode == wire::kModePwm ? 1 : 2;
    if (static_cast<uint16_t>(i) + 1 + width > len) return fail(wire::kErrBadLength, wire::kTick);
    if (mode == wire::kModeServo) {
      const uint16_t us = read_u16(body + i + 1);
      if (us < wire::kServoMinUs || us > wire::kServoMaxUs) return fail(wire::kErrBadValue, pin);
    }
    i = static_cast<uint8_t>(i + 1 + width);
  }
  return kOk;
}

}  // namespace hilswarm
