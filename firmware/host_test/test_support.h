// Helpers shared by the host tests and the libFuzzer target.
#ifndef HILSWARM_HOST_TEST_SUPPORT_H
#define HILSWARM_HOST_TEST_SUPPORT_H

#include <stdint.h>

#include <string>
#include <vector>

#include "engine.h"
#include "frame_builder.h"
#include "frame_parser.h"

namespace test {

using Bytes = std::vector<uint8_t>;

Bytes from_hex(const std::string& hex);
std::string to_hex(const Bytes& bytes);

// Wire frame of a payload: COBS(payload || crc16_le) || 0x00 (any length).
Bytes frame(const Bytes& payload);

// xorshift64*: deterministic, seeded.
struct Rng {
  uint64_t state;
  explicit Rng(uint64_t seed) : state(seed ? seed : 0x9E3779B97F4A7C15ULL) {}
  uint32_t next();
  uint32_t below(uint32_t n) { return n ? next() % n : 0; }
  bool chance(uint32_t percent) { return below(100) < percent; }
};

// The firmware's receive path on the host: parser -> engine -> builder. Every reply frame the
// engine builds is parsed back with an independent FrameParser and kept as a payload.
struct Link {
  hilswarm::Engine engine{hilswarm::FirmwareVersion{1, 0}};
  hilswarm::FrameParser parser;
  hilswarm::FrameBuilder builder;
  hilswarm::FrameParser reply_parser;
  uint32_t now_ms = 0;
  uint32_t now_us = 0;
  long dropped = 0;             // frames dropped silently
  long reply_framing_errors = 0;
  std::vector<Bytes> replies;   // reply payloads, in order

  void boot(bool hw_watchdog_reset = false);
  void feed(const Bytes& bytes);
  void feed_byte(uint8_t byte);
  // Sends one request payload; returns the single reply payload (empty if none or several).
  Bytes request(const Bytes& payload);
};

}  // namespace test

#endif  // HILSWARM_HOST_TEST_SUPPORT_H
