#include "engine.h"

#include "hal.h"

namespace hilswarm {

void Engine::begin(bool hw_watchdog_reset, uint32_t now_ms) {
  for (uint8_t pin = 0; pin < wire::kPinCount; ++pin) {
    config_[pin].mode = wire::kModeUnused;
    config_[pin].safe = 0;
  }
  flags_ = wire::kStatusReset | wire::kStatusNotConfigured;
  if (hw_watchdog_reset) flags_ |= wire::kStatusHwWatchdogReset;
  watchdog_ms_ = 0;
  bcast_id_ = 0;
  last_rx_ms_ = now_ms;
  link_tripped_ = false;
  derive_pin_sets();
}

void Engine::derive_pin_sets() {
  sets_ = pin_sets(config_);
  n_out_ = 0;
  n_wide_ = 0;
  uint8_t values = 0;
  for (uint8_t pin = 0; pin < wire::kPinCount; ++pin) {
    const uint8_t mode = config_[pin].mode;
    if (mode == wire::kModeDigitalOut) out_pins_[n_out_++] = pin;
    if (mode == wire::kModePwm || mode == wire::kModeServo) {
      wide_pins_[n_wide_++] = pin;
      values = static_cast<uint8_t>(values + (mode == wire::kModeServo ? 2 : 1));
    }
  }
  section_len_ = static_cast<uint8_t>((n_out_ + 7) / 8 + values);
}

void Engine::drive_safe() {
  for (uint8_t pin = 0; pin < wire::kPinCount; ++pin) {
    const PinConfig& c = config_[pin];
    switch (c.mode) {
      case wire::kModeDigitalOut:
        hal::write_digital(pin, static_cast<uint8_t>(c.safe));
        break;
      case wire::kModePwm:
        hal::write_pwm(pin, static_cast<uint8_t>(c.safe));
        break;
      case wire::kModeServo:
        hal::write_servo(pin, c.safe);
        break;
      default:
        break;
    }
  }
}

void Engine::trip_watchdog() {
  drive_safe();
  flags_ |= wire::kStatusWatchdogTripped;
  link_tripped_ = true;
}

void Engine::error(uint8_t seq, uint8_t code, uint8_t detail, FrameBuilder& out) {
  out.begin(wire::kError, seq);
  out.put_u8(code);
  out.put_u8(detail);
}

void Engine::frame_too_long(FrameBuilder& out) {
  flags_ |= wire::kStatusRxErrors;
  error(0, wire::kErrFrameTooLong, 0, out);
}

bool Engine::handle(const uint8_t* payload, uint8_t len, uint32_t now_ms, uint32_t now_us,
                    FrameBuilder& out) {
  // The firmware's way for a TICK (so the host tests check it against every golden vector):
  // prepared, then committed; respond() whenever that does not apply.
  bool reply = true;
  if (!(prepare(payload, len, now_us, out) && commit(payload, len, now_ms))) {
    reply = respond(payload, len, now_ms, now_us, out);
  }
  apply_pending();
  return reply;
}

bool Engine::prepare(const uint8_t* payload, uint8_t len, uint32_t now_us, FrameBuilder& out) {
  prepared_payload_ = nullptr;
  if (len < 2 || payload[0] != wire::kTick || (flags_ & wire::kStatusNotConfigured)) {
    return false;
  }
  const uint8_t* body = payload + 2;
  if (!check_tick(body, static_cast<uint8_t>(len - 2), config_, sets_).ok()) return false;
  build_tick_reply(payload[1], body, flags_, now_us, out);  // flags_ = what take_status() gives
  prepared_payload_ = payload;
  prepared_len_ = len;
  prepared_flags_ = flags_;
  return true;
}

bool Engine::respond(const uint8_t* payload, uint8_t len, uint32_t now_ms, uint32_t now_us,
                     FrameBuilder& out) {
  pending_body_ = nullptr;
  prepared_payload_ = nullptr;
  // A late frame first reports the silence it ends, then feeds the watchdog.
  poll(now_ms);
  const uint8_t type = payload[0];
  const uint8_t seq = payload[1];
  const uint8_t* body = payload + 2;
  const uint8_t body_len = static_cast<uint8_t>(len - 2);
  if (type == wire::kBcast) return on_bcast(seq, body, body_len, now_ms, now_us, out);
  last_rx_ms_ = now_ms;
  link_tripped_ = false;

  switch (type) {
    case wire::kHello:
      on_hello(seq, body_len, out);
      break;
    case wire::kConfig:
      on_config(seq, body, body_len, out);
      break;
    case wire::kTick:
      on_tick(seq, body, body_len, now_us, out);
      break;
    case wire::kEstop:
      on_estop(seq, body_len, out);
      break;
    case wire::kSetId:
      on_set_id(seq, body, body_len, out);
      break;
    default:
      error(seq, wire::kErrUnknownType, type, out);
      break;
  }
  return true;
}

bool Engine::on_bcast(uint8_t seq, const uint8_t* body, uint8_t len, uint32_t now_ms,
                      uint32_t now_us, FrameBuilder& out) {
  // Every board hears a broadcast: never an ERROR (the answers would collide on the air). A
  // frame without a section of ours is none of our business: it does not feed the watchdog, so
  // a robot the broadcasts leave out goes safe as one whose link is silent.
  if (bcast_id_ == 0 || (flags_ & wire::kStatusNotConfigured)) return false;
  uint8_t hdr = 0;
  const int16_t at = find_section(body, len, bcast_id_, &hdr);
  if (at == kNoSection) return false;
  if (at < 0 || (hdr & wire::kBcastLengthMask) != section_len_ || !section_ok(body + at)) {
    flags_ |= wire::kStatusRxErrors;  // dropped as a damaged frame would be
    return false;
  }
  last_rx_ms_ = now_ms;
  link_tripped_ = false;
  if (!(flags_ & wire::kStatusEstopped)) {  // e-stopped: samples only, writes ignored
    pending_body_ = body + at;
    pending_len_ = section_len_;
    pending_section_ = true;
  }
  if (!(hdr & wire::kBcastReplyFlag)) return false;
  out.begin(wire::kBcast | wire::kReplyBit, seq);
  out.put_u8(take_status());
  out.put_u32(now_us);
  put_samples(sets_.input, out);
  return true;
}

bool Engine::section_ok(const uint8_t* data) const {
  uint8_t i = static_cast<uint8_t>((n_out_ + 7) / 8);
  for (uint8_t k = 0; k < n_wide_; ++k) {
    if (config_[wide_pins_[k]].mode == wire::kModeServo) {
      const uint16_t us = read_u16(data + i);
      if (us < wire::kServoMinUs || us > wire::kServoMaxUs) return false;
      i = static_cast<uint8_t>(i + 2);
    } else {
      i = static_cast<uint8_t>(i + 1);
    }
  }
  return true;
}

void Engine::on_hello(uint8_t seq, uint8_t body_len, FrameBuilder& out) {
  if (body_len != 0) return error(seq, wire::kErrBadLength, wire::kHello, out);
  out.begin(wire::kHello | wire::kReplyBit, seq);
  out.put_u8(wire::kProtocolVersion);
  out.put_u8(version_.major);
  out.put_u8(version_.minor);
  out.put_u16(hal::load_board_id());
  out.put_u8(take_status());
  out.put_u8(wire::kPinCount);
  for (uint8_t pin = 0; pin < wire::kPinCount; ++pin) out.put_u8(pin_capabilities(pin));
  flags_ &= static_cast<uint8_t>(~(wire::kStatusReset | wire::kStatusHwWatchdogReset));
}

void Engine::on_config(uint8_t seq, const uint8_t* body, uint8_t len, FrameBuilder& out) {
  PinConfig next[wire::kPinCount];
  uint16_t watchdog_ms = 0;
  uint8_t n_entries = 0;
  uint8_t bcast_id = 0;
  const RequestError e = check_config(body, len, next, &watchdog_ms, &n_entries, &bcast_id);
  if (!e.ok()) return error(seq, e, out);

  // Release every pin whose mode changes before taking new ones (no transient Timer1 clash).
  for (uint8_t pin = 0; pin < wire::kPinCount; ++pin) {
    if (config_[pin].mode != next[pin].mode && config_[pin].mode != wire::kModeUnused) {
      hal::set_pin_mode(pin, wire::kModeUnused);
    }
  }
  for (uint8_t pin = 0; pin < wire::kPinCount; ++pin) {
    if (config_[pin].mode != next[pin].mode && next[pin].mode != wire::kModeUnused) {
      hal::set_pin_mode(pin, next[pin].mode);
    }
    config_[pin] = next[pin];
  }
  derive_pin_sets();
  drive_safe();
  watchdog_ms_ = watchdog_ms;
  bcast_id_ = bcast_id;
  link_tripped_ = false;
  flags_ &= static_cast<uint8_t>(~(wire::kStatusEstopped | wire::kStatusNotConfigured));

  out.begin(wire::kConfig | wire::kReplyBit, seq);
  out.put_u8(take_status());
  out.put_u8(n_entries);
}

void Engine::on_tick(uint8_t seq, const uint8_t* body, uint8_t len, uint32_t now_us,
                     FrameBuilder& out) {
  if (flags_ & wire::kStatusNotConfigured) {
    return error(seq, wire::kErrNotConfigured, wire::kTick, out);
  }
  const RequestError e = check_tick(body, len, config_, sets_);
  if (!e.ok()) return error(seq, e, out);

  if (!(flags_ & wire::kStatusEstopped)) {  // e-stopped: samples only, writes ignored
    pending_body_ = body;
    pending_len_ = len;
    pending_section_ = false;
  }

  // Samples first: they do not depend on this TICK's writes (inputs only), and the reply can
  // leave before the writes are applied.
  build_tick_reply(seq, body, take_status(), now_us, out);
}

void Engine::build_tick_reply(uint8_t seq, const uint8_t* body, uint8_t status, uint32_t now_us,
                              FrameBuilder& out) {
  out.begin(wire::kTick | wire::kReplyBit, seq);
  out.put_u8(status);
  out.put_u32(now_us);
  put_samples(body + 3, out);
}

void Engine::put_samples(const uint8_t* mask, FrameBuilder& out) {
  for (uint8_t first = 0; first < wire::kPinCount; first = static_cast<uint8_t>(first + 8)) {
    uint8_t bits = mask[first / 8];  // no mask bit beyond the last pin (check_tick, PinSets)
    for (uint8_t pin = first; bits != 0; ++pin, bits = static_cast<uint8_t>(bits >> 1)) {
      if (!(bits & 1U)) continue;
      if (config_[pin].mode == wire::kModeAnalogIn) {
        out.put_u16(hal::read_analog(pin));
      } else {
        out.put_u16(hal::read_digital(pin));
      }
    }
  }
}

void Engine::apply_pending() {
  const uint8_t* body = pending_body_;
  if (body == nullptr) return;
  pending_body_ = nullptr;
  if (pending_section_) {  // our BCAST section: levels by DIGITAL_OUT index, then every value
    for (uint8_t k = 0; k < n_out_; ++k) {
      hal::write_digital(out_pins_[k], (body[k / 8] & pin_bit(k)) ? 1 : 0);
    }
    uint8_t i = static_cast<uint8_t>((n_out_ + 7) / 8);
    for (uint8_t k = 0; k < n_wide_; ++k) {
      const uint8_t pin = wide_pins_[k];
      if (config_[pin].mode == wire::kModeServo) {
        hal::write_servo(pin, read_u16(body + i));
        i = static_cast<uint8_t>(i + 2);
      } else {
        hal::write_pwm(pin, body[i]);
        i = static_cast<uint8_t>(i + 1);
      }
    }
    return;
  }
  // Every DIGITAL_OUT pin gets its dout level (the cached list: no walk over every pin).
  for (uint8_t k = 0; k < n_out_; ++k) {
    const uint8_t pin = out_pins_[k];
    hal::write_digital(pin, (body[pin / 8] & pin_bit(pin)) ? 1 : 0);
  }
  // Then the PWM and servo writes, in wire order (check_tick validated every one of them).
  uint8_t i = kTickHeader;
  while (i < pending_len_) {
    const uint8_t pin = body[i];
    if (config_[pin].mode == wire::kModePwm) {
      hal::write_pwm(pin, body[i + 1]);
      i = static_cast<uint8_t>(i + 2);
    } else {
      hal::write_servo(pin, read_u16(body + i + 1));
      i = static_cast<uint8_t>(i + 3);
    }
  }
}

void Engine::on_estop(uint8_t seq, uint8_t body_len, FrameBuilder& out) {
  if (body_len != 0) return error(seq, wire::kErrBadLength, wire::kEstop, out);
  drive_safe();
  flags_ |= wire::kStatusEstopped;
  out.begin(wire::kEstop | wire::kReplyBit, seq);
  out.put_u8(take_status());
}

void Engine::on_set_id(uint8_t seq, const uint8_t* body, uint8_t len, FrameBuilder& out) {
  if (len != 2) return error(seq, wire::kErrBadLength, wire::kSetId, out);
  hal::store_board_id(read_u16(body));
  out.begin(wire::kSetId | wire::kReplyBit, seq);
  out.put_u16(hal::load_board_id());
}

}  // namespace hilswarm
