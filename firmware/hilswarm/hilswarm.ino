// hilswarm firmware for ATmega328P Arduino boards (Uno, Duemilanove, Fio).
// Speaks docs/protocol.md over the hardware serial port: one checked frame per control tick.
// Build with firmware/Makefile (plain avr-gcc against Debian's arduino-core-avr).
#include <Arduino.h>
#include <avr/wdt.h>

#include "boot_reason.h"
#include "engine.h"
#include "firmware_config.h"
#include "frame_builder.h"
#include "frame_parser.h"

namespace {

hilswarm::FrameParser parser;
hilswarm::FrameBuilder builder;
hilswarm::Engine engine({hilswarm::config::kFirmwareMajor, hilswarm::config::kFirmwareMinor});
uint32_t next_periodic_us = 0;
// The reply prepared for the frame being received, should it turn out to be `payload_length`
// bytes long (see on_data_byte).
struct PreparedReply {
  bool built;            // engine.prepare() built it into `builder`
  const uint8_t* frame;  // its wire frame once stamped and framed; nullptr: not yet
  size_t frame_length;
  uint8_t payload_length;
};
PreparedReply prepared = {false, nullptr, 0, 0};
// Payload length of the last TICK answered: a host sends the same kind of TICK every tick.
uint8_t last_tick_length = 0;
// Board time of the frame being received [us] (TICK_REPLY's board_time_us): when its last byte
// before the delimiter was in.
uint32_t frame_time_us = 0;

void send_reply() {
  size_t n = 0;
  const uint8_t* frame = builder.finish(&n);
  Serial.write(frame, n);
}

void drop_prepared() {
  prepared.built = false;
  prepared.frame = nullptr;
  engine.cancel_prepared();
}

bool prepare(uint8_t payload_length, uint32_t now_us) {
  prepared.frame = nullptr;
  prepared.built = engine.prepare(parser.payload(), payload_length, now_us, builder);
  prepared.payload_length = payload_length;
  return prepared.built;
}

// A byte arrives every ~87 us at 115200 baud and the CPU is idle in between, so a TICK's reply
// is ready before its delimiter arrives and the delimiter only commits it: it is built (checked,
// sampled) as soon as the payload is as long as the last TICK's (the CRC bytes follow), and
// stamped with the board time and framed (CRC, COBS) when the bytes so far are a whole CRC-valid
// frame, one byte time before the delimiter. (A first TICK, or one of a new length, is built
// then too.)
void on_data_byte() {
  const uint8_t decoded = parser.decoded_length();
  if (parser.could_end_here()) {
    frame_time_us = micros();
    const uint8_t n = parser.candidate_length();
    if (prepared.built && prepared.payload_length == n) {
      hilswarm::Engine::restamp(frame_time_us, builder);
    } else if (!prepare(n, frame_time_us)) {
      return;
    }
    prepared.frame = builder.finish(&prepared.frame_length);
  } else if (decoded == last_tick_length && parser.payload()[0] == hilswarm::wire::kTick) {
    if (!prepared.built || prepared.payload_length != decoded) prepare(decoded, 0);
  } else if (prepared.built && decoded >= prepared.payload_length + 2) {
    drop_prepared();  // the frame went on past the prepared payload and its CRC
  }
}

// The delimiter of a frame whose reply is ready: commit and send the reply before the parser
// even closes the frame (could_end_here() already checked everything a delimiter makes final).
// True if the reply was sent.
bool send_prepared_reply() {
  if (prepared.frame == nullptr || !parser.could_end_here() ||
      parser.candidate_length() != prepared.payload_length ||
      !engine.commit(parser.payload(), prepared.payload_length, millis())) {
    return false;
  }
  Serial.write(prepared.frame, prepared.frame_length);
  return true;
}

void on_frame(bool answered) {
  const uint8_t* payload = parser.payload();
  const uint8_t length = parser.payload_length();
  // A BCAST that does not ask this board for a reply is answered by nothing.
  if (!answered && engine.respond(payload, length, millis(), frame_time_us, builder)) {
    send_reply();
  }
  prepared.built = false;
  prepared.frame = nullptr;
  if (payload[0] == hilswarm::wire::kTick) last_tick_length = length;
  // The TICK's (or our BCAST section's) outputs are driven while the reply's first byte is on
  // the wire: the writes add nothing to the round trip.
  engine.apply_pending();
}

void on_byte(uint8_t byte) {
  const bool answered = byte == hilswarm::wire::kDelimiter && send_prepared_reply();
  switch (parser.feed(byte)) {
    case hilswarm::FrameParser::kFrame:
      on_frame(answered);
      break;
    case hilswarm::FrameParser::kTooLong:
      drop_prepared();
      engine.frame_too_long(builder);
      send_reply();
      break;
    case hilswarm::FrameParser::kTooShort:
    case hilswarm::FrameParser::kBadCobs:
    case hilswarm::FrameParser::kBadCrc:
      drop_prepared();
      engine.rx_error();
      break;
    case hilswarm::FrameParser::kNone:
      if (byte != hilswarm::wire::kDelimiter) {
        on_data_byte();
      } else {
        drop_prepared();  // an idle delimiter
      }
      break;
  }
}

void run_periodic(uint32_t now_us) {
  using hilswarm::config::kMaxLagPeriods;
  using hilswarm::config::kPeriodUs;
  if (static_cast<int32_t>(now_us - next_periodic_us) < 0) return;
  next_periodic_us += kPeriodUs;  // drift-free: the schedule, not the wake-up, sets the next run
  const int32_t lag_us = static_cast<int32_t>(now_us - next_periodic_us);
  if (lag_us > static_cast<int32_t>(kMaxLagPeriods * kPeriodUs)) {
    next_periodic_us = now_us + kPeriodUs;  // stalled: restart the schedule, no catch-up burst
  }
  engine.poll(millis());
}

}  // namespace

void setup() {
  wdt_enable(hilswarm::config::kHwWatchdogTimeout);
  Serial.begin(hilswarm::config::kBaud);
  engine.begin(hilswarm::boot::hw_watchdog_reset(), millis());
  next_periodic_us = micros() + hilswarm::config::kPeriodUs;
}

void loop() {
  wdt_reset();
  // Handle the bytes waiting, and those arriving meanwhile (a delimiter that arrives while a reply
  // is being prepared is handled at once), at most kMaxBytesPerLoop per loop so the periodic work
  // still runs.
  for (uint8_t n = 0; n < hilswarm::config::kMaxBytesPerLoop && Serial.available() > 0; ++n) {
    const int c = Serial.read();
    if (c < 0) break;
    on_byte(static_cast<uint8_t>(c));
  }
  run_periodic(micros());
}
