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

void send_reply() {
  size_t n = 0;
  const uint8_t* frame = builder.finish(&n);
  Serial.write(frame, n);
}

void on_byte(uint8_t byte) {
  switch (parser.feed(byte)) {
    case hilswarm::FrameParser::kFrame:
      engine.handle(parser.payload(), parser.payload_length(), millis(), micros(), builder);
      send_reply();
      break;
    case hilswarm::FrameParser::kTooLong:
      engine.frame_too_long(builder);
      send_reply();
      break;
    case hilswarm::FrameParser::kTooShort:
    case hilswarm::FrameParser::kBadCobs:
    case hilswarm::FrameParser::kBadCrc:
      engine.rx_error();
      break;
    case hilswarm::FrameParser::kNone:
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
  // Drain every byte that is waiting now (bounded: bytes arriving meanwhile wait one loop).
  for (int pending = Serial.available(); pending > 0; --pending) {
    const int c = Serial.read();
    if (c < 0) break;
    on_byte(static_cast<uint8_t>(c));
  }
  run_periodic(micros());
}
