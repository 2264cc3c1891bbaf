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

  // Answers one CRC-valid payload (type, seq, body): one reply or ERROR is built into `out`,
  // and a TICK's (or our BCAST section's) writes are applied. Any valid frame but a BCAST feeds
  // the link watchdog (after checking it for a trip); a BCAST feeds it only when it holds a
  // valid section of ours. Returns false when nothing is to be sent: a BCAST that does not ask
  // this board for a reply (a broadcast is never answered with ERROR). Same as respond()
  // followed by apply_pending().
  bool handle(const uint8_t* payload, uint8_t len, uint32_t now_ms, uint32_t now_us,
              FrameBuilder& out);

  // handle() in two halves, so the firmware can start sending the reply before it drives the
  // outputs (the writes then cost no turnaround time: they are done long before the reply's last
  // byte has left). respond() does everything but a valid TICK's writes: it validates the TICK,
  // takes its samples and builds its reply, and remembers where the writes are. apply_pending()
  // applies them; it must be called before `payload` changes (the firmware calls it right after
  // queueing the reply, before reading the next byte). Does nothing if there are none.
  bool respond(const uint8_t* payload, uint8_t len, uint32_t now_ms, uint32_t now_us,
               FrameBuilder& out);
  void apply_pending();

  // A TICK's reply prepared before its frame is known to be complete (the firmware calls this
  // in the byte times before the delimiter, see hilswarm.ino). prepare() builds
  // into `out` exactly the reply respond() would build for `payload` at `now_us` if the status
  // does not change meanwhile, and changes nothing else; false (and `out` undefined) for
  // anything but a TICK that passes every check. commit() is called once the frame is
  // complete: if it is the prepared payload and the status is still the same after the link
  // watchdog check, it does the rest of what respond() does (feeds the watchdog, clears the
  // reported events, remembers the writes) and returns true: the prepared reply is the answer.
  // Otherwise it returns false having done at most that watchdog check, and the caller answers
  // with respond() (which then builds the same reply it would have built anyway).
  bool prepare(const uint8_t* payload, uint8_t len, uint32_t now_us, FrameBuilder& out);
  // (Inline: it runs between a TICK's delimiter and the first byte of its reply.)
  bool commit(const uint8_t* payload, uint8_t len, uint32_t now_ms) {
    const bool same_frame = prepared_payload_ == payload && prepared_len_ == len;
    prepared_payload_ = nullptr;
    if (!same_frame) return false;
    poll(now_ms);  // as respond(): a late frame first reports the silence it ends
    if (flags_ != prepared_flags_) return false;
    last_rx_ms_ = now_ms;
    link_tripped_ = false;
    take_status();
    pending_body_ = (flags_ & wire::kStatusEstopped) ? nullptr : payload + 2;
    pending_len_ = static_cast<uint8_t>(len - 2);
    pending_section_ = false;
    return true;
  }
  // Sets the board time of the reply prepare() built in `out` to `now_us` (before finish()): the
  // firmware prepares a TICK's reply early and stamps it when the frame's last byte is in.
  // (TICK_REPLY payload: type, seq, status, board_time_us at offset 3.)
  static void restamp(uint32_t now_us, FrameBuilder& out) { out.patch_u32(3, now_us); }
  void cancel_prepared() { prepared_payload_ = nullptr; }

  // A frame longer than the maximum arrived: ERROR FRAME_TOO_LONG with seq 0 into `out`.
  void frame_too_long(FrameBuilder& out);

  // A frame was dropped silently (CRC, framing, too short): flag RX_ERRORS.
  void rx_error() { flags_ |= wire::kStatusRxErrors; }

  // Periodic work: trips the link watchdog once the silence since the last valid frame exceeds
  // `watchdog_ms` (1 ms resolution).
  void poll(uint32_t now_ms) {
    if (watchdog_ms_ == 0 || link_tripped_ || (flags_ & wire::kStatusNotConfigured)) return;
    if (now_ms - last_rx_ms_ > watchdog_ms_) trip_watchdog();  // silence *exceeds* the timeout
  }

  // Observers (tests).
  uint8_t peek_status() const { return flags_; }
  const PinConfig& pin(uint8_t p) const { return config_[p]; }
  uint16_t watchdog_ms() const { return watchdog_ms_; }
  uint8_t bcast_id() const { return bcast_id_; }
  uint8_t section_length() const { return section_len_; }

 private:
  void on_hello(uint8_t seq, uint8_t body_len, FrameBuilder& out);
  void on_config(uint8_t seq, const uint8_t* body, uint8_t len, FrameBuilder& out);
  void on_tick(uint8_t seq, const uint8_t* body, uint8_t len, uint32_t now_us,
               FrameBuilder& out);
  void build_tick_reply(uint8_t seq, const uint8_t* body, uint8_t status, uint32_t now_us,
                        FrameBuilder& out);
  void on_estop(uint8_t seq, uint8_t body_len, FrameBuilder& out);
  void on_set_id(uint8_t seq, const uint8_t* body, uint8_t len, FrameBuilder& out);
  bool on_bcast(uint8_t seq, const uint8_t* body, uint8_t len, uint32_t now_ms, uint32_t now_us,
                FrameBuilder& out);
  bool section_ok(const uint8_t* data) const;  // servo values in range (length checked before)
  void put_samples(const uint8_t* mask, FrameBuilder& out);  // u16 per mask bit, ascending
  void error(uint8_t seq, uint8_t code, uint8_t detail, FrameBuilder& out);
  void error(uint8_t seq, RequestError e, FrameBuilder& out) { error(seq, e.code, e.detail, out); }
  uint8_t take_status() {  // current flags; clears the one-shot events
    const uint8_t status = flags_;
    flags_ &= static_cast<uint8_t>(~wire::kStatusEvents);
    return status;
  }
  void drive_safe();
  void trip_watchdog();    // outputs safe, WATCHDOG_TRIPPED reported until the next valid frame
  void derive_pin_sets();  // sets_, out_pins_, n_out_ from config_ (after every change)

  FirmwareVersion version_;
  PinConfig config_[wire::kPinCount] = {};
  // Derived from config_ once per CONFIG for the TICK hot path.
  PinSets sets_ = {{0, 0, 0}, {0, 0, 0}, {0, 0, 0}, {0, 0, 0}};
  uint8_t out_pins_[wire::kPinCount] = {};  // DIGITAL_OUT pins, ascending
  uint8_t n_out_ = 0;
  uint8_t wide_pins_[wire::kPinCount] = {};  // PWM and SERVO pins, ascending (BCAST sections)
  uint8_t n_wide_ = 0;
  uint8_t section_len_ = 0;  // data bytes of our BCAST section: levels, then PWM/servo values
  uint8_t bcast_id_ = 0;     // our BCAST id (CONFIG, protocol 2); 0 = not in broadcasts
  // The validated TICK body whose writes respond() left for apply_pending() (nullptr: none).
  const uint8_t* pending_body_ = nullptr;
  uint8_t pending_len_ = 0;
  bool pending_section_ = false;  // pending_body_ is our BCAST section, not a TICK body
  // The payload prepare() answered (nullptr: none), its length and the status it reported.
  const uint8_t* prepared_payload_ = nullptr;
  uint8_t prepared_len_ = 0;
  uint8_t prepared_flags_ = 0;
  uint8_t flags_ = 0;
  uint16_t watchdog_ms_ = 0;
  uint32_t last_rx_ms_ = 0;
  bool link_tripped_ = false;  // outputs went safe for silence; re-armed by the next valid frame
};

}  // namespace hilswarm

#endif  // HILSWARM_PROTOCOL_ENGINE_H
