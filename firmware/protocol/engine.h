// The protocol engine: status flags, pin configuration, link watchdog, e-stop latch, and the
// answer to every request. Board-independent (talks to the board through hal.h); time is passed
// in, so the host tests drive it with a fake clock.
#ifndef HILSWARM_PROTOCOL_ENGINE_H
#define HILSWARM_PROTOCOL_ENGINE_H

#include <stdint.h>

#include "frame_builder.h"
#include "requests.h"
#include "wire.h"

namespace hilswarm {

struct FirmwareVersion {
  uint8_t major;
  uint8_t minor;
};

class Engine {
 public:
  explicit Engine(FirmwareVersion version) : version_(version) {}

  // Boot: every pin UNUSED, status RESET | NOT_CONFIGURED (| HW_WATCHDOG_RESET).
  void begin(bool hw_watchdog_reset, uint32_t now_ms);

  // Answers one CRC-valid payload (type, seq, body): exactly one reply or ERROR is built into
  // `out`. Any valid frame feeds the link watchdog (after checking it for a trip).
  void handle(const uint8_t* payload, uint8_t len, uint32_t now_ms, uint32_t now_us,
              FrameBuilder& out);

  // A frame longer than the maximum arrived: ERROR FRAME_TOO_LONG with seq 0 into `out`.
  void frame_too_long(FrameBuilder& out);

  // A frame was dropped silently (CRC, framing, too short): flag RX_ERRORS.
  void rx_error() { flags_ |= wire::kStatusRxErrors; }

  // Periodic work: trips the link watchdog once the silence since the last valid frame exceeds
  // `watchdog_ms` (1 ms resolution).
  void poll(uint32_t now_ms);

  // Observers (tests).
  uint8_t peek_status() const { return flags_; }
  const PinConfig& pin(uint8_t p) const { return config_[p]; }
  uint16_t watchdog_ms() const { return watchdog_ms_; }

 private:
  void on_hello(uint8_t seq, uint8_t body_len, FrameBuilder& out);
  void on_config(uint8_t seq, const uint8_t* body, uint8_t len, FrameBuilder& out);
  void on_tick(uint8_t seq, const uint8_t* body, uint8_t len, uint32_t now_us,
               FrameBuilder& out);
  void on_estop(uint8_t seq, uint8_t body_len, FrameBuilder& out);
  void on_set_id(uint8_t seq, const uint8_t* body, uint8_t len, FrameBuilder& out);
  void error(uint8_t seq, uint8_t code, uint8_t detail, FrameBuilder& out);
  void error(uint8_t seq, RequestError e, FrameBuilder& out) { error(seq, e.code, e.detail, out); }
  uint8_t take_status();   // current flags; clears the one-shot events
  void drive_safe();

  FirmwareVersion version_;
  PinConfig config_[wire::kPinCount] = {};
  uint8_t flags_ = 0;
  uint16_t watchdog_ms_ = 0;
  uint32_t last_rx_ms_ = 0;
  bool link_tripped_ = false;  // outputs went safe for silence; re-armed by the next valid frame
};

}  // namespace hilswarm

#endif  // HILSWARM_PROTOCOL_ENGINE_H
