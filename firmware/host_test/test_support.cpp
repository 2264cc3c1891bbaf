#include "test_support.h"

#include <stdexcept>

#include "cobs.h"
#include "crc16.h"
#include "fake_hal.h"

namespace test {

Bytes from_hex(const std::string& hex) {
  if (hex.size() % 2) throw std::runtime_error("odd hex string: " + hex);
  Bytes out;
  for (size_t i = 0; i < hex.size(); i += 2) {
    out.push_back(static_cast<uint8_t>(std::stoul(hex.substr(i, 2), nullptr, 16)));
  }
  return out;
}

std::string to_hex(const Bytes& bytes) {
  static const char* digits = "0123456789abcdef";
  std::string s;
  for (uint8_t b : bytes) {
    s += digits[b >> 4];
    s += digits[b & 15];
  }
  return s;
}

Bytes frame(const Bytes& payload) {
  Bytes raw = payload;
  const uint16_t crc = hilswarm::crc16(payload.data(), payload.size());
  raw.push_back(static_cast<uint8_t>(crc));
  raw.push_back(static_cast<uint8_t>(crc >> 8));
  Bytes out(hilswarm::cobs_max_encoded(raw.size()) + 1);
  const size_t n = hilswarm::cobs_encode(raw.data(), raw.size(), out.data(), out.size());
  out.resize(n);
  out.push_back(0);
  return out;
}

uint32_t Rng::next() {
  state ^= state >> 12;
  state ^= state << 25;
  state ^= state >> 27;
  return static_cast<uint32_t>((state * 0x2545F4914F6CDD1DULL) >> 32);
}

void Link::boot(bool hw_watchdog_reset) {
  engine.begin(hw_watchdog_reset, now_ms);
  parser.reset();
  reply_parser.reset();
  replies.clear();
}

void Link::feed_byte(uint8_t byte) {
  bool send = false;
  switch (parser.feed(byte)) {
    case hilswarm::FrameParser::kFrame:
      send = engine.handle(parser.payload(), parser.payload_length(), now_ms, now_us, builder);
      break;
    case hilswarm::FrameParser::kTooLong:
      engine.frame_too_long(builder);
      send = true;
      break;
    case hilswarm::FrameParser::kTooShort:
    case hilswarm::FrameParser::kBadCobs:
    case hilswarm::FrameParser::kBadCrc:
      engine.rx_error();
      ++dropped;
      break;
    case hilswarm::FrameParser::kNone:
      break;
  }
  if (!send) return;
  size_t n = 0;
  const uint8_t* wire = builder.finish(&n);
  if (builder.overflow()) ++reply_framing_errors;
  for (size_t i = 0; i < n; ++i) {
    const auto r = reply_parser.feed(wire[i]);
    if (r == hilswarm::FrameParser::kFrame) {
      replies.emplace_back(reply_parser.payload(),
                           reply_parser.payload() + reply_parser.payload_length());
    } else if (r != hilswarm::FrameParser::kNone || (i + 1 == n) != (wire[i] == 0)) {
      ++reply_framing_errors;
    }
  }
}

void Link::feed(const Bytes& bytes) {
  for (uint8_t b : bytes) feed_byte(b);
}

Bytes Link::request(const Bytes& payload) {
  const size_t before = replies.size();
  feed(frame(payload));
  if (replies.size() != before + 1) return Bytes();
  return replies.back();
}

}  // namespace test
