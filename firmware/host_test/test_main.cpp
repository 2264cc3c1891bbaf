// Host tests of the firmware's protocol code (built with ASan + UBSan by `make host-test`):
// CRC and COBS reference vectors, the byte-fed parser, the frame builder, the golden vectors
// shared with the Python codec (firmware/protocol/golden_vectors.json), the engine's answer to
// every kind of request, and a bounded, seeded random fuzz loop.
//
//   test_protocol --vectors PATH [--fuzz-frames N] [--seed S]
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <map>
#include <stdexcept>
#include <string>
#include <vector>

#include "cobs.h"
#include "crc16.h"
#include "fake_hal.h"
#include "frame_builder.h"
#include "frame_parser.h"
#include "mini_json.h"
#include "requests.h"
#include "test_support.h"
#include "wire.h"

using test::Bytes;
namespace wire = hilswarm::wire;

// ---------------------------------------------------------------- a tiny check framework

namespace {

long g_checks = 0;
long g_failures = 0;
std::string g_test;

void check(bool ok, const std::string& what) {
  ++g_checks;
  if (ok) return;
  ++g_failures;
  if (g_failures <= 50) std::fprintf(stderr, "FAIL [%s] %s\n", g_test.c_str(), what.c_str());
}

template <typename A, typename B>
void check_eq(const A& got, const B& want, const std::string& what) {
  check(static_cast<long long>(got) == static_cast<long long>(want),
        what + ": got " + std::to_string(static_cast<long long>(got)) + ", want " +
            std::to_string(static_cast<long long>(want)));
}

void check_bytes(const Bytes& got, const Bytes& want, const std::string& what) {
  check(got == want, what + ": got " + test::to_hex(got) + ", want " + test::to_hex(want));
}

// Bounds-checked reply access: a short reply is a failure, not a crash of the test.
uint8_t at(const Bytes& reply, size_t i) {
  if (i < reply.size()) return reply[i];
  check(false, "reply " + test::to_hex(reply) + " has no byte " + std::to_string(i));
  return 0xEE;
}
uint16_t u16(const Bytes& reply, size_t i) {
  return static_cast<uint16_t>(at(reply, i) | at(reply, i + 1) << 8);
}

// ---------------------------------------------------------------- request builders

struct Entry {
  uint8_t pin, mode;
  uint16_t safe;
};

Bytes hello(uint8_t seq) { return {wire::kHello, seq}; }
Bytes estop(uint8_t seq) { return {wire::kEstop, seq}; }
Bytes set_id(uint8_t seq, uint16_t id) {
  return {wire::kSetId, seq, static_cast<uint8_t>(id), static_cast<uint8_t>(id >> 8)};
}
Bytes config(uint8_t seq, uint16_t watchdog_ms, const std::vector<Entry>& entries) {
  Bytes p = {wire::kConfig, seq, static_cast<uint8_t>(watchdog_ms),
             static_cast<uint8_t>(watchdog_ms >> 8)};
  for (const Entry& e : entries) {
    p.insert(p.end(), {e.pin, e.mode, static_cast<uint8_t>(e.safe),
                       static_cast<uint8_t>(e.safe >> 8)});
  }
  return p;
}
Bytes tick(uint8_t seq, uint32_t dout, uint32_t rmask, const Bytes& writes = {}) {
  Bytes p = {wire::kTick,
             seq,
             static_cast<uint8_t>(dout),
             static_cast<uint8_t>(dout >> 8),
             static_cast<uint8_t>(dout >> 16),
             static_cast<uint8_t>(rmask),
             static_cast<uint8_t>(rmask >> 8),
             static_cast<uint8_t>(rmask >> 16)};
  p.insert(p.end(), writes.begin(), writes.end());
  return p;
}
Bytes pwm_write(uint8_t pin, uint8_t duty) { return {pin, duty}; }
Bytes servo_write(uint8_t pin, uint16_t us) {
  return {pin, static_cast<uint8_t>(us), static_cast<uint8_t>(us >> 8)};
}
Bytes cat(std::initializer_list<Bytes> parts) {
  Bytes out;
  for (const Bytes& b : parts) out.insert(out.end(), b.begin(), b.end());
  return out;
}

void check_error(const Bytes& reply, uint8_t seq, uint8_t code, uint8_t detail,
                 const std::string& what) {
  check(reply.size() == 4 && at(reply, 0) == wire::kError && at(reply, 1) == seq && at(reply, 2) == code &&
            at(reply, 3) == detail,
        what + ": want ERROR seq " + std::to_string(seq) + " code " + std::to_string(code) +
            " detail " + std::to_string(detail) + ", got " + test::to_hex(reply));
}

void check_reply(const Bytes& reply, uint8_t type, uint8_t seq, const std::string& what) {
  check(reply.size() >= 2 && at(reply, 0) == (type | wire::kReplyBit) && at(reply, 1) == seq,
        what + ": want reply type " + std::to_string(type | 0x80) + " seq " +
            std::to_string(seq) + ", got " + test::to_hex(reply));
}

uint8_t status_of(const Bytes& reply) { return reply.size() > 2 ? at(reply, 2) : 0xFF; }

// The Blimpduino-like configuration used by several tests.
const std::vector<Entry> kBlimp = {
    {2, wire::kModeDigitalOut, 0}, {4, wire::kModeDigitalOut, 1},
    {7, wire::kModeDigitalOut, 0}, {8, wire::kModeDigitalOut, 0},
    {5, wire::kModePwm, 0},        {6, wire::kModePwm, 17},
    {9, wire::kModeServo, 1500},   {14, wire::kModeAnalogIn, 0},
    {3, wire::kModeDigitalIn, 0},  {12, wire::kModeDigitalInPullup, 0},
};

// ---------------------------------------------------------------- CRC, COBS, parser, builder

void test_crc() {
  const char* s = "123456789";
  check_eq(hilswarm::crc16(reinterpret_cast<const uint8_t*>(s), 9), 0x29B1, "check value");
  check_eq(hilswarm::crc16(nullptr, 0), 0xFFFF, "empty input = init");
}

void test_cobs() {
  const struct {
    const char* raw;
    const char* enc;
  } vectors[] = {
      {"00", "0101"},         {"0000", "010101"},       {"11220033", "0311220233"},
      {"11223344", "0511223344"}, {"11000000", "0211010101"}, {"", "01"},
  };
  for (const auto& v : vectors) {
    const Bytes raw = test::from_hex(v.raw);
    Bytes out(raw.size() + 8);
    const size_t n = hilswarm::cobs_encode(raw.data(), raw.size(), out.data(), out.size());
    out.resize(n);
    check_bytes(out, test::from_hex(v.enc), std::string("encode ") + v.raw);
  }
  // 254 and 255 non-zero bytes: the 0xFF block has no implied zero.
  Bytes run254, run255;
  for (int i = 1; i <= 254; ++i) run254.push_back(static_cast<uint8_t>(i));
  run255 = run254;
  run255.push_back(0xFF);
  Bytes out(300);
  size_t n = hilswarm::cobs_encode(run254.data(), run254.size(), out.data(), out.size());
  check(n == 256 && out[0] == 0xFF && out[255] == 0x01, "254-byte run: FF block + 01");
  n = hilswarm::cobs_encode(run255.data(), run255.size(), out.data(), out.size());
  check(n == 257 && out[0] == 0xFF && out[255] == 0x02 && out[256] == 0xFF, "255-byte run");
  check_eq(hilswarm::cobs_encode(run255.data(), run255.size(), out.data(), 10), 0,
           "encode refuses a too small buffer");

  // Round trip of random data through the streaming decoder.
  test::Rng rng(7);
  for (int round = 0; round < 2000; ++round) {
    Bytes raw(rng.below(600));
    for (auto& b : raw) b = rng.chance(30) ? 0 : static_cast<uint8_t>(rng.next());
    Bytes enc(hilswarm::cobs_max_encoded(raw.size()));
    enc.resize(hilswarm::cobs_encode(raw.data(), raw.size(), enc.data(), enc.size()));
    bool zero_free = true;
    for (uint8_t b : enc) zero_free = zero_free && b != 0;
    check(zero_free, "encoding contains no zero");
    uint8_t buf[255];
    hilswarm::CobsDecoder dec(buf, sizeof(buf));
    for (uint8_t b : enc) dec.feed(b);
    check(dec.complete(), "decoder sees a complete encoding");
    check(dec.overflow() == (raw.size() > sizeof(buf)), "overflow exactly when too long");
    if (!dec.overflow()) {
      check_bytes(Bytes(buf, buf + dec.length()), raw, "round trip");
    }
  }
}

test::Bytes feed_until_result(hilswarm::FrameParser& p, const Bytes& wire_bytes,
                              std::vector<hilswarm::FrameParser::Result>* results) {
  Bytes payload;
  for (uint8_t b : wire_bytes) {
    const auto r = p.feed(b);
    if (r != hilswarm::FrameParser::kNone) results->push_back(r);
    if (r == hilswarm::FrameParser::kFrame) {
      payload.assign(p.payload(), p.payload() + p.payload_length());
    }
  }
  return payload;
}

void test_parser() {
  using P = hilswarm::FrameParser;
  P parser;
  std::vector<P::Result> results;

  Bytes payload = hello(42);
  check_bytes(feed_until_result(parser, test::frame(payload), &results), payload, "HELLO");
  check(results.size() == 1 && results[0] == P::kFrame, "one frame result");

  // Garbage (without zeros) glued to the front of a frame is one bad frame; the next is fine.
  results.clear();
  Bytes stream = {0x13, 0x37, 0xAB};
  Bytes f = test::frame(payload);
  stream.insert(stream.end(), f.begin(), f.end());
  stream.insert(stream.end(), f.begin(), f.end());
  feed_until_result(parser, stream, &results);
  check(results.size() == 2 && results[0] != P::kFrame && results[1] == P::kFrame,
        "garbage costs exactly the frame it touches");

  // Idle line: consecutive delimiters are not frames and not errors.
  results.clear();
  feed_until_result(parser, Bytes(10, 0), &results);
  check(results.empty(), "empty frames are ignored");

  // Limits: 96-byte payload passes, 97 bytes is too long; 5000 non-zero bytes stay bounded.
  Bytes big(wire::kMaxPayload, 0x55);
  results.clear();
  check_bytes(feed_until_result(parser, test::frame(big), &results), big, "max payload");
  big.push_back(0x55);
  results.clear();
  feed_until_result(parser, test::frame(big), &results);
  check(results.size() == 1 && results[0] == P::kTooLong, "97-byte payload is too long");
  results.clear();
  Bytes flood(5000, 0x01);
  flood.push_back(0);
  feed_until_result(parser, flood, &results);
  check(results.size() == 1 && results[0] == P::kTooLong, "flood without delimiter");

  results.clear();
  feed_until_result(parser, test::frame({0x01}), &results);
  check(results.size() == 1 && results[0] == P::kTooShort, "3 decoded bytes is too short");
  results.clear();
  feed_until_result(parser, {0x05, 0x01, 0x02, 0x00}, &results);
  check(results.size() == 1 && results[0] == P::kBadCobs, "truncated COBS block");
  results.clear();
  Bytes bad = test::frame(hello(1));
  bad[2] ^= 0x40;
  feed_until_result(parser, bad, &results);
  check(results.size() == 1 && results[0] == P::kBadCrc, "flipped bit fails the CRC");
}

void test_builder() {
  hilswarm::FrameBuilder b;
  b.begin(0x83, 7);
  b.put_u8(0x09);
  b.put_u32(0xFFFFFFFFu);
  b.put_u16(0x0100);
  b.put_u24(0x0A0B0C);
  check_bytes(Bytes(b.payload(), b.payload() + b.payload_length()),
              test::from_hex("830709ffffffff00010c0b0a"), "little-endian fields");
  size_t n = 0;
  const uint8_t* w = b.finish(&n);
  check_bytes(Bytes(w, w + n),
              test::frame(Bytes(b.payload(), b.payload() + b.payload_length())),
              "finish = COBS(payload + CRC) + 0x00");
  b.begin(1, 2);
  for (int i = 0; i < wire::kMaxPayload - 2; ++i) b.put_u8(0);
  check(!b.overflow(), "96 bytes fit");
  b.put_u8(1);
  check(b.overflow() && b.payload_length() == wire::kMaxPayload, "97th byte overflows");
}

// ---------------------------------------------------------------- golden vectors

hilswarm::FrameParser::Result drop_reason(const std::string& reason) {
  if (reason == "crc") return hilswarm::FrameParser::kBadCrc;
  if (reason == "short") return hilswarm::FrameParser::kTooShort;
  if (reason == "cobs") return hilswarm::FrameParser::kBadCobs;
  if (reason == "too_long") return hilswarm::FrameParser::kTooLong;
  throw std::runtime_error("golden vectors: unknown drop_reason '" + reason + "'");
}

// Checks the engine's effect of a TICK vector against its `fields` (writes, dout, rmask).
void check_tick_fields(const test::Link& link, const Bytes& reply, const mini_json::Value& fields,
                       const std::string& name) {
  const uint32_t dout = static_cast<uint32_t>(fields["dout"].integer());
  const uint32_t rmask = static_cast<uint32_t>(fields["rmask"].integer());
  for (int pin = 0; pin < 20; ++pin) {
    if (fake::board.mode[pin] == wire::kModeDigitalOut) {
      check_eq(fake::board.digital_out[pin], (dout >> pin) & 1,
               name + ": level of D" + std::to_string(pin));
    }
  }
  for (const auto& w : fields["writes"].array) {
    const int pin = static_cast<int>(w["pin"].integer());
    const long long value = w["value"].integer();
    if (w["mode"].str() == "PWM") {
      check_eq(fake::board.pwm[pin], value, name + ": PWM of pin " + std::to_string(pin));
    } else {
      check_eq(fake::board.servo[pin], value, name + ": servo of pin " + std::to_string(pin));
    }
  }
  int n = 0;
  for (int pin = 0; pin < 24; ++pin) n += (rmask >> pin) & 1;
  check_eq(reply.size(), 7 + 2 * n, name + ": reply carries one u16 per rmask bit");
  (void)link;
}

void test_golden(const std::string& path) {
  const mini_json::Value doc = mini_json::parse_file(path);
  check_eq(doc["protocol_version"].integer(), wire::kProtocolVersion, "protocol_version");
  const auto& vectors = doc["vectors"].array;
  check(vectors.size() >= 20, "at least 20 golden vectors");

  std::vector<const mini_json::Value*> configs, ticks;
  long frames = 0, drops = 0;
  for (const auto& v : vectors) {
    const std::string name = v["name"].str();
    const Bytes wire_bytes = test::from_hex(v["wire_hex"].str());
    const Bytes payload = test::from_hex(v["payload_hex"].str());
    hilswarm::FrameParser parser;
    std::vector<hilswarm::FrameParser::Result> results;
    const Bytes got = feed_until_result(parser, wire_bytes, &results);
    if (v["valid"].boolean) {
      ++frames;
      check(results.size() == 1 && results[0] == hilswarm::FrameParser::kFrame,
            name + ": parser returns exactly one frame");
      check_bytes(got, payload, name + ": parsed payload");
      hilswarm::FrameBuilder b;
      b.begin(payload[0], payload[1]);
      for (size_t i = 2; i < payload.size(); ++i) b.put_u8(payload[i]);
      size_t n = 0;
      const uint8_t* w = b.finish(&n);
      check_bytes(Bytes(w, w + n), wire_bytes, name + ": frame builder output");
      if (v["direction"].str() == "host_to_board") {
        if (payload[0] == wire::kConfig) configs.push_back(&v);
        if (payload[0] == wire::kTick) ticks.push_back(&v);
      }
    } else {
      ++drops;
      const auto want = drop_reason(v["fields"]["drop_reason"].str());
      check(results.size() == 1 && results[0] == want, name + ": dropped for the stated reason");
    }
  }
  check(frames > 0 && drops > 0, "golden vectors hold valid and invalid frames");

  // Requests: the engine answers each valid request vector as the protocol says.
  test::Link link;
  for (const auto& v : vectors) {
    if (!v["valid"].boolean || v["direction"].str() != "host_to_board") continue;
    const std::string name = v["name"].str();
    const Bytes payload = test::from_hex(v["payload_hex"].str());
    const auto& fields = v["fields"];
    if (payload[0] == wire::kTick || payload[0] == wire::kBcast) continue;  // below
    fake::reset();
    link.boot();
    const Bytes reply = link.request(payload);
    check_reply(reply, payload[0], payload[1], name);
    if (payload[0] == wire::kHello) {
      // Compare with the HELLO_REPLY vector of an Uno after boot (same capabilities/status).
      for (const auto& r : vectors) {
        if (r["name"].str() != "hello_reply_uno") continue;
        const Bytes want = test::from_hex(r["payload_hex"].str());
        check(reply.size() == want.size(), name + ": HELLO_REPLY size");
        check_eq(at(reply, 2), wire::kProtocolVersion, name + ": protocol version");
        check_eq(at(reply, 7), want[7], name + ": status after boot");
        check_bytes(Bytes(reply.begin() + 8, reply.end()), Bytes(want.begin() + 8, want.end()),
                    name + ": n_pins and capabilities");
      }
    } else if (payload[0] == wire::kConfig) {
      check_eq(reply.size(), 4, name + ": CONFIG_REPLY size");
      check_eq(at(reply, 3), fields["pins"].array.size(), name + ": n_configured");
      for (const auto& pin : fields["pins"].array) {
        const int p = static_cast<int>(pin["pin"].integer());
        check_eq(fake::board.mode[p], link.engine.pin(static_cast<uint8_t>(p)).mode,
                 name + ": mode applied to pin " + std::to_string(p));
      }
    } else if (payload[0] == wire::kSetId) {
      check_eq(u16(reply, 2), fields["board_id"].integer(), name + ": id");
    } else if (payload[0] == wire::kEstop) {
      check(status_of(reply) & wire::kStatusEstopped, name + ": ESTOPPED");
    }
  }
  for (const auto* t : ticks) {
    const std::string name = (*t)["name"].str();
    const Bytes payload = test::from_hex((*t)["payload_hex"].str());
    bool answered = false;
    for (const auto* c : configs) {
      fake::reset();
      link.boot();
      link.request(test::from_hex((*c)["payload_hex"].str()));
      const Bytes reply = link.request(payload);
      if (reply.size() < 2 || at(reply, 0) != (wire::kTick | wire::kReplyBit)) continue;
      answered = true;
      check_reply(reply, wire::kTick, payload[1], name);
      check_tick_fields(link, reply, (*t)["fields"], name + " after " + (*c)["name"].str());
      break;
    }
    check(answered, name + ": some CONFIG vector makes this TICK valid");
  }
  // BCAST vectors (protocol 2): each board configured by the named CONFIG vector applies only
  // its own section, and answers only when its section asks.
  long bcasts = 0;
  for (const auto& v : vectors) {
    if (!v["valid"].boolean || v["fields"]["type"].str() != "BCAST") continue;
    const std::string name = v["name"].str();
    const Bytes payload = test::from_hex(v["payload_hex"].str());
    for (const auto& e : v["expect"].array) {
      const std::string config_name = e["config"].str();
      const long long id = e["board_id"].integer();
      bool found = false;
      for (const auto* c : configs) {
        if ((*c)["name"].str() != config_name) continue;
        found = true;
        fake::reset();
        link.boot();
        check_reply(link.request(test::from_hex((*c)["payload_hex"].str())), wire::kConfig,
                    static_cast<uint8_t>(test::from_hex((*c)["payload_hex"].str())[1]),
                    name + ": " + config_name);
        check_eq(link.engine.bcast_id(), id, name + ": broadcast id from " + config_name);
        const size_t before = link.replies.size();
        link.feed(test::frame(payload));
        bool asked = false;
        for (const auto& s : v["fields"]["sections"].array) {
          if (s["board_id"].integer() == id) asked = s["reply"].boolean;
        }
        check_eq(link.replies.size() - before, asked ? 1 : 0, name + ": replies of board " +
                                                                   std::to_string(id));
        if (asked && link.replies.size() == before + 1) {
          const Bytes& r = link.replies.back();
          check_reply(r, wire::kBcast, payload[1], name);
          check_eq(r.size(), 9, name + ": status, time and the A0 sample");
        }
        const uint32_t dout = static_cast<uint32_t>(e["dout"].integer());
        for (int pin = 0; pin < 20; ++pin) {
          if (fake::board.mode[pin] == wire::kModeDigitalOut) {
            check_eq(fake::board.digital_out[pin], (dout >> pin) & 1,
                     name + ": board " + std::to_string(id) + " D" + std::to_string(pin));
          }
        }
        for (const auto& w : e["pwm"].array) {
          const int pin = static_cast<int>(w["pin"].integer());
          check_eq(fake::board.pwm[pin], w["value"].integer(),
                   name + ": board " + std::to_string(id) + " PWM " + std::to_string(pin));
        }
        ++bcasts;
      }
      check(found, name + ": CONFIG vector " + config_name + " exists");
    }
  }
  check(bcasts >= 6, "every BCAST vector checked on every board it names");
  check_eq(fake::board.violations, 0, "fake board saw no illegal pin operation");
  std::printf("golden vectors: %zu (%ld frames, %ld drops, %zu configs, %zu ticks) from %s\n",
              vectors.size(), frames, drops, configs.size(), ticks.size(), path.c_str());
}

// ---------------------------------------------------------------- engine

void test_engine_boot_and_hello() {
  fake::reset();
  test::Link link;
  link.boot(false);
  Bytes r = link.request(hello(1));
  check_reply(r, wire::kHello, 1, "HELLO");
  check(r.size() == 9 + 20 && at(r, 8) == 20, "HELLO_REPLY has 20 capabilities");
  check_eq(at(r, 2), 2, "protocol version");
  check_eq(at(r, 3), 1, "fw major");
  check_eq(at(r, 4), 0, "fw minor (the test link says 1.0)");
  check_eq(at(r, 7), wire::kStatusReset | wire::kStatusNotConfigured, "status after boot");
  r = link.request(hello(2));
  check_eq(at(r, 7), wire::kStatusNotConfigured, "HELLO cleared RESET");
  check_error(link.request({wire::kHello, 3, 0}), 3, wire::kErrBadLength, wire::kHello,
              "HELLO with a body");

  link.boot(true);
  r = link.request(hello(4));
  check_eq(at(r, 7), wire::kStatusReset | wire::kStatusNotConfigured | wire::kStatusHwWatchdogReset,
           "status after a hardware watchdog reset");
  r = link.request(hello(5));
  check_eq(at(r, 7), wire::kStatusNotConfigured, "HELLO cleared HW_WATCHDOG_RESET");

  const uint8_t unknown[] = {0x00, 0x07, 0x7E, 0x7F, 0x81, 0x83, 0xFF};
  for (uint8_t t : unknown) {
    check_error(link.request({t, 9}), 9, wire::kErrUnknownType, t,
                "unknown type " + std::to_string(t));
  }
  check_error(link.request(tick(10, 0, 0)), 10, wire::kErrNotConfigured, wire::kTick,
              "TICK before CONFIG");
  check_eq(fake::board.violations, 0, "no illegal pin operation");
}

void test_engine_config_errors() {
  fake::reset();
  test::Link link;
  link.boot();
  const long writes = fake::board.writes;
  struct Case {
    const char* what;
    Bytes payload;
    uint8_t code, detail;
  };
  const Case cases[] = {
      {"body of 1 byte", {wire::kConfig, 1, 0}, wire::kErrBadLength, wire::kConfig},
      {"body of 4 bytes", {wire::kConfig, 1, 0, 0, 5, 1}, wire::kErrBadLength, wire::kConfig},
      {"body of 5 bytes", {wire::kConfig, 1, 0, 0, 5, 2, 0}, wire::kErrBadLength, wire::kConfig},
      {"body of 8 bytes", {wire::kConfig, 1, 0, 0, 5, 2, 0, 0, 9, 1}, wire::kErrBadLength,
       wire::kConfig},
      {"pin 20", config(1, 0, {{20, wire::kModeDigitalOut, 0}}), wire::kErrBadPin, 20},
      {"pin 255", config(1, 0, {{255, wire::kModeDigitalOut, 0}}), wire::kErrBadPin, 255},
      {"serial pin 0", config(1, 0, {{0, wire::kModeUnused, 0}}), wire::kErrBadPin, 0},
      {"serial pin 1", config(1, 0, {{1, wire::kModeDigitalIn, 0}}), wire::kErrBadPin, 1},
      {"pin listed twice",
       config(1, 0, {{5, wire::kModePwm, 0}, {6, wire::kModePwm, 0}, {5, wire::kModePwm, 0}}),
       wire::kErrBadPin, 5},
      {"unknown mode", config(1, 0, {{5, 7, 0}}), wire::kErrBadMode, 5},
      {"PWM on pin 4", config(1, 0, {{4, wire::kModePwm, 0}}), wire::kErrBadMode, 4},
      {"SERVO on pin 5", config(1, 0, {{5, wire::kModeServo, 1500}}), wire::kErrBadMode, 5},
      {"ANALOG_IN on pin 13", config(1, 0, {{13, wire::kModeAnalogIn, 0}}), wire::kErrBadMode,
       13},
      {"PWM on A0", config(1, 0, {{14, wire::kModePwm, 0}}), wire::kErrBadMode, 14},
      {"servo 9 + PWM 10",
       config(1, 0, {{10, wire::kModePwm, 0}, {9, wire::kModeServo, 1500}}),
       wire::kErrPinConflict, 10},
      {"servo 10 + PWM 9",
       config(1, 0, {{9, wire::kModePwm, 0}, {10, wire::kModeServo, 1500}}),
       wire::kErrPinConflict, 9},
      {"digital safe 2", config(1, 0, {{13, wire::kModeDigitalOut, 2}}), wire::kErrBadValue,
       13},
      {"PWM safe 256", config(1, 0, {{3, wire::kModePwm, 256}}), wire::kErrBadValue, 3},
      {"servo safe 499", config(1, 0, {{9, wire::kModeServo, 499}}), wire::kErrBadValue, 9},
      {"servo safe 2501", config(1, 0, {{10, wire::kModeServo, 2501}}), wire::kErrBadValue, 10},
      // Check order: pins before modes before the conflict before safe values.
      {"bad pin wins over bad mode", config(1, 0, {{5, 9, 0}, {20, 2, 0}}), wire::kErrBadPin,
       20},
      {"bad mode wins over conflict",
       config(1, 0, {{9, wire::kModeServo, 1500}, {10, wire::kModePwm, 0}, {4, wire::kModePwm, 0}}),
       wire::kErrBadMode, 4},
      {"conflict wins over bad value",
       config(1, 0, {{13, wire::kModeDigitalOut, 7}, {9, wire::kModeServo, 1500},
                     {10, wire::kModePwm, 0}}),
       wire::kErrPinConflict, 10},
  };
  for (const Case& c : cases) {
    check_error(link.request(c.payload), 1, c.code, c.detail, std::string("CONFIG ") + c.what);
  }
  check_eq(fake::board.writes, writes, "rejected CONFIGs drove nothing");
  check(link.engine.peek_status() & wire::kStatusNotConfigured, "still NOT_CONFIGURED");
  for (int p = 0; p < 20; ++p) check_eq(fake::board.mode[p], 0, "pin modes untouched");

  // Accepted corner cases.
  Bytes r = link.request(config(2, 0, {{9, wire::kModeServo, 500}, {10, wire::kModeServo, 2500}}));
  check_reply(r, wire::kConfig, 2, "two servos");
  r = link.request(config(3, 0, {{2, wire::kModeDigitalIn, 4321}, {15, wire::kModeUnused, 9}}));
  check_reply(r, wire::kConfig, 3, "input safe values are ignored");
  r = link.request(config(4, 0, {{9, wire::kModePwm, 255}, {10, wire::kModePwm, 0}}));
  check_reply(r, wire::kConfig, 4, "PWM on both Timer1 pins without a servo");
  check_eq(fake::board.violations, 0, "no illegal pin operation");
}

void test_engine_config_and_tick() {
  fake::reset();
  test::Link link;
  link.boot();
  Bytes r = link.request(config(1, 0, kBlimp));
  check_reply(r, wire::kConfig, 1, "CONFIG blimp");
  check_eq(r.size(), 4, "CONFIG_REPLY size");
  check_eq(at(r, 2), wire::kStatusReset, "CONFIG cleared NOT_CONFIGURED (RESET stays until HELLO)");
  check_eq(at(r, 3), kBlimp.size(), "n_configured");
  for (const Entry& e : kBlimp) check_eq(fake::board.mode[e.pin], e.mode, "mode applied");
  check_eq(fake::board.digital_out[4], 1, "safe level of D4");
  check_eq(fake::board.digital_out[2], 0, "safe level of D2");
  check_eq(fake::board.pwm[6], 17, "safe duty of D6");
  check_eq(fake::board.servo[9], 1500, "safe pulse of D9");

  fake::board.analog_in[14] = 777;
  fake::board.digital_in[3] = 1;
  fake::board.digital_in[12] = 0;
  link.now_us = 123456789;
  r = link.request(tick(2, (1u << 2) | (1u << 8), (1u << 14) | (1u << 3) | (1u << 12),
                        cat({pwm_write(5, 200), servo_write(9, 2100), pwm_write(6, 0)})));
  check_reply(r, wire::kTick, 2, "TICK");
  check_eq(r.size(), 2 + 1 + 4 + 3 * 2, "TICK_REPLY size");
  check_eq(at(r, 2), wire::kStatusReset, "TICK status");
  check_eq(static_cast<uint32_t>(at(r, 3) | at(r, 4) << 8 | at(r, 5) << 16 | static_cast<uint32_t>(at(r, 6)) << 24),
           123456789u, "board time");
  check_eq(u16(r, 7), 1, "D3 sample (ascending pin order)");
  check_eq(u16(r, 9), 0, "D12 sample");
  check_eq(u16(r, 11), 777, "A0 sample");
  check_eq(fake::board.digital_out[2], 1, "D2 high");
  check_eq(fake::board.digital_out[4], 0, "D4 low (every DIGITAL_OUT pin is written)");
  check_eq(fake::board.digital_out[8], 1, "D8 high");
  check_eq(fake::board.pwm[5], 200, "PWM 5");
  check_eq(fake::board.pwm[6], 0, "PWM 6");
  check_eq(fake::board.servo[9], 2100, "servo 9");

  const long writes = fake::board.writes;
  struct Case {
    const char* what;
    Bytes payload;
    uint8_t code, detail;
  };
  const Case cases[] = {
      {"body of 5 bytes", {wire::kTick, 3, 0, 0, 0, 0, 0}, wire::kErrBadLength, wire::kTick},
      {"dout on a PWM pin", tick(3, 1u << 5, 0), wire::kErrBadPin, 5},
      {"dout on an input", tick(3, 1u << 3, 0), wire::kErrBadPin, 3},
      {"dout bit 21", tick(3, 1u << 21, 0), wire::kErrBadPin, 21},
      {"rmask on an output", tick(3, 0, 1u << 2), wire::kErrBadPin, 2},
      {"rmask on a serial pin", tick(3, 0, 1u << 0), wire::kErrBadPin, 0},
      {"rmask on an unused pin", tick(3, 0, 1u << 19), wire::kErrBadPin, 19},
      {"rmask bit 23", tick(3, 0, 1u << 23), wire::kErrBadPin, 23},
      {"write to a digital pin", tick(3, 0, 0, pwm_write(2, 1)), wire::kErrBadPin, 2},
      {"write to pin 30", tick(3, 0, 0, pwm_write(30, 1)), wire::kErrBadPin, 30},
      {"truncated PWM write", tick(3, 0, 0, {5}), wire::kErrBadLength, wire::kTick},
      {"truncated servo write", tick(3, 0, 0, {9, 0xDC}), wire::kErrBadLength, wire::kTick},
      {"servo 499 us", tick(3, 0, 0, servo_write(9, 499)), wire::kErrBadValue, 9},
      {"servo 2501 us", tick(3, 0, 0, servo_write(9, 2501)), wire::kErrBadValue, 9},
      // Order: dout, rmask, then each write in wire order.
      {"dout before rmask", tick(3, 1u << 5, 1u << 2), wire::kErrBadPin, 5},
      {"rmask before writes", tick(3, 0, 1u << 2, pwm_write(2, 0)), wire::kErrBadPin, 2},
      {"writes in wire order",
       tick(3, 0, 0, cat({pwm_write(5, 1), servo_write(9, 3000), pwm_write(2, 0)})),
       wire::kErrBadValue, 9},
      {"a good write then a bad one", tick(3, 1u << 2, 0, cat({pwm_write(5, 9), {9}})),
       wire::kErrBadLength, wire::kTick},
  };
  for (const Case& c : cases) {
    check_error(link.request(c.payload), 3, c.code, c.detail, std::string("TICK ") + c.what);
  }
  check_eq(fake::board.writes, writes, "rejected TICKs drove nothing");
  check_eq(fake::board.pwm[5], 200, "PWM 5 unchanged");
  check_eq(fake::board.violations, 0, "no illegal pin operation");
}

void test_engine_estop() {
  fake::reset();
  test::Link link;
  link.boot();
  link.request(config(1, 0, kBlimp));
  link.request(tick(2, 1u << 2, 0, cat({pwm_write(5, 99), servo_write(9, 1000)})));
  Bytes r = link.request(estop(3));
  check_reply(r, wire::kEstop, 3, "ESTOP");
  check(status_of(r) & wire::kStatusEstopped, "ESTOPPED latched");
  check_eq(fake::board.digital_out[2], 0, "D2 safe");
  check_eq(fake::board.pwm[5], 0, "PWM 5 safe");
  check_eq(fake::board.servo[9], 1500, "servo 9 safe");
  const long writes = fake::board.writes;
  fake::board.analog_in[14] = 321;
  r = link.request(tick(4, 1u << 2, 1u << 14, pwm_write(5, 200)));
  check_reply(r, wire::kTick, 4, "TICK while estopped");
  check(status_of(r) & wire::kStatusEstopped, "TICK reports ESTOPPED");
  check_eq(u16(r, 7), 321, "samples still taken");
  check_eq(fake::board.writes, writes, "writes ignored while estopped");
  check_error(link.request(tick(5, 1u << 5, 0)), 5, wire::kErrBadPin, 5,
              "bad TICK still answered with ERROR while estopped");
  r = link.request(config(6, 0, kBlimp));
  check(!(status_of(r) & wire::kStatusEstopped), "CONFIG clears ESTOPPED");
  link.request(tick(7, 0, 0, pwm_write(5, 201)));
  check_eq(fake::board.pwm[5], 201, "writes applied again after CONFIG");
  check_error(link.request({wire::kEstop, 8, 1}), 8, wire::kErrBadLength, wire::kEstop,
              "ESTOP with a body");
  check_eq(fake::board.violations, 0, "no illegal pin operation");
}

void test_engine_watchdog() {
  fake::reset();
  test::Link link;
  link.now_ms = 1000;
  link.boot();
  link.request(hello(1));
  link.request(config(2, 100, kBlimp));
  link.request(tick(3, 1u << 2, 0, cat({pwm_write(5, 77), servo_write(9, 2000)})));
  link.now_ms += 100;
  link.engine.poll(link.now_ms);
  check_eq(fake::board.pwm[5], 77, "no trip at exactly 100 ms");
  link.now_ms += 1;
  link.engine.poll(link.now_ms);
  check_eq(fake::board.pwm[5], 0, "trip once the silence exceeds 100 ms: PWM safe");
  check_eq(fake::board.servo[9], 1500, "servo safe");
  check_eq(fake::board.digital_out[2], 0, "digital safe");
  const long writes = fake::board.writes;
  link.now_ms += 1000;
  link.engine.poll(link.now_ms);
  check_eq(fake::board.writes, writes, "a trip drives the outputs once");
  Bytes r = link.request(tick(4, 0, 0, pwm_write(5, 55)));
  check_eq(status_of(r), wire::kStatusWatchdogTripped, "next reply reports the trip");
  check_eq(fake::board.pwm[5], 55, "a TICK after a trip is applied");
  r = link.request(tick(5, 0, 0));
  check_eq(status_of(r), 0, "the trip is reported once");

  // A frame arriving late reports the silence it ends (no poll in between).
  link.now_ms += 250;
  r = link.request(tick(6, 0, 0, pwm_write(5, 66)));
  check_eq(status_of(r), wire::kStatusWatchdogTripped, "late TICK reports the trip");
  check_eq(fake::board.pwm[5], 66, "and is applied");

  // Any valid frame feeds the watchdog; millis() wrap-around is harmless.
  link.now_ms = 0xFFFFFFF0u;
  link.request(tick(7, 0, 0, pwm_write(5, 66)));
  link.now_ms += 50;  // wraps
  link.engine.poll(link.now_ms);
  check_eq(fake::board.pwm[5], 66, "no trip across the millis() wrap");

  // watchdog_ms = 0 disables it.
  link.request(config(8, 0, kBlimp));
  link.request(tick(9, 0, 0, pwm_write(5, 12)));
  link.now_ms += 100000;
  link.engine.poll(link.now_ms);
  check_eq(fake::board.pwm[5], 12, "watchdog 0 never trips");
  check_eq(fake::board.violations, 0, "no illegal pin operation");
}

void test_engine_rx_errors_and_id() {
  fake::reset();
  test::Link link;
  link.boot();
  link.request(hello(1));
  Bytes bad = test::frame(hello(2));
  bad[1] ^= 0x01;
  link.feed(bad);
  check_eq(link.replies.size(), 1, "a bad CRC is never answered");
  Bytes r = link.request(hello(3));
  check_eq(at(r, 7), wire::kStatusNotConfigured | wire::kStatusRxErrors, "RX_ERRORS reported");
  r = link.request(hello(4));
  check_eq(at(r, 7), wire::kStatusNotConfigured, "RX_ERRORS reported once");

  link.feed(test::frame(Bytes(120, 0x42)));
  check_error(link.replies.back(), 0, wire::kErrFrameTooLong, 0, "too long frame");
  r = link.request(set_id(5, 0xBEEF));
  check_reply(r, wire::kSetId, 5, "SET_ID");
  check_eq(u16(r, 2), 0xBEEF, "id read back");
  r = link.request(hello(6));
  check_eq(at(r, 7), wire::kStatusNotConfigured | wire::kStatusRxErrors,
           "RX_ERRORS of the long frame survives replies without status");
  check_eq(u16(r, 5), 0xBEEF, "HELLO reports the id");
  fake::reset(true);
  link.boot();
  r = link.request(hello(7));
  check_eq(u16(r, 5), 0xBEEF, "id survives a reboot");
  check_error(link.request({wire::kSetId, 8, 1}), 8, wire::kErrBadLength, wire::kSetId,
              "SET_ID of 1 byte");
  check_error(link.request({wire::kSetId, 9, 1, 2, 3}), 9, wire::kErrBadLength, wire::kSetId,
              "SET_ID of 3 bytes");
}

// ---------------------------------------------------------------- broadcast (protocol 2)

// A Frisbee-like board: D4/D7/D8/D12 out, PWM 5/6, servo 9, A0 in; section = 1 + 2 + 2 = 5 B.
const std::vector<Entry> kBcastBoard = {
    {4, wire::kModeDigitalOut, 0}, {7, wire::kModeDigitalOut, 0}, {8, wire::kModeDigitalOut, 1},
    {12, wire::kModeDigitalOut, 0}, {5, wire::kModePwm, 0}, {6, wire::kModePwm, 3},
    {9, wire::kModeServo, 1500}, {14, wire::kModeAnalogIn, 0},
};

Bytes config_id(uint8_t seq, uint16_t watchdog_ms, const std::vector<Entry>& entries,
                uint8_t id) {
  Bytes p = config(seq, watchdog_ms, entries);
  p.push_back(id);
  return p;
}

Bytes section(uint8_t id, bool reply, const Bytes& data) {
  Bytes s = {id, static_cast<uint8_t>(data.size() | (reply ? wire::kBcastReplyFlag : 0))};
  s.insert(s.end(), data.begin(), data.end());
  return s;
}

Bytes bcast(uint8_t seq, const std::vector<Bytes>& sections) {
  Bytes p = {wire::kBcast, seq};
  for (const Bytes& s : sections) p.insert(p.end(), s.begin(), s.end());
  return p;
}

// Section data for kBcastBoard: levels (bit j = j-th DIGITAL_OUT pin), PWM5, PWM6, servo9.
Bytes bcast_data(uint8_t levels, uint8_t pwm5, uint8_t pwm6, uint16_t servo9) {
  return {levels, pwm5, pwm6, static_cast<uint8_t>(servo9), static_cast<uint8_t>(servo9 >> 8)};
}

size_t feed_count(test::Link& link, const Bytes& payload) {
  const size_t before = link.replies.size();
  link.feed(test::frame(payload));
  return link.replies.size() - before;
}

void test_engine_broadcast() {
  fake::reset();
  test::Link link;
  link.now_ms = 1000;
  link.boot();
  link.request(hello(0));  // clears RESET
  // Not configured (and no id): a BCAST is ignored, never answered.
  check_eq(feed_count(link, bcast(1, {section(2, true, bcast_data(1, 1, 1, 1000))})), 0,
           "BCAST before CONFIG: silence");
  // A CONFIG of protocol 1 (no trailing byte) leaves the board out of broadcasts.
  link.request(config(2, 100, kBcastBoard));
  check_eq(link.engine.bcast_id(), 0, "no trailing byte: broadcast id 0");
  check_eq(link.engine.section_length(), 5, "section: 1 level byte + 2 PWM + 1 servo");
  check_eq(feed_count(link, bcast(3, {section(0, true, bcast_data(1, 1, 1, 1000))})), 0,
           "id 0 never matches");
  check_error(link.request(Bytes{wire::kConfig, 4, 0, 0, 1, 2}), 4, wire::kErrBadLength,
              wire::kConfig, "CONFIG body of 2 + 4n + 2 bytes");
  Bytes r = link.request(config_id(5, 100, kBcastBoard, 7));
  check_reply(r, wire::kConfig, 5, "CONFIG with broadcast id 7");
  check_eq(at(r, 3), kBcastBoard.size(), "the id byte is no pin entry");
  check_eq(link.engine.bcast_id(), 7, "broadcast id 7 stored with the configuration");

  // Our section among others: only ours applied; the reply only when asked for.
  fake::board.analog_in[14] = 444;
  const long writes = fake::board.writes;
  check_eq(feed_count(link, bcast(6, {section(3, true, bcast_data(0x0F, 9, 9, 2500)),
                                      section(7, false, bcast_data(0x05, 10, 20, 1000)),
                                      section(8, true, Bytes{1, 2})})),
           0, "our section does not ask: no reply");
  check(fake::board.writes > writes, "our section applied");
  check_eq(fake::board.digital_out[4], 1, "level bit 0 -> D4");
  check_eq(fake::board.digital_out[7], 0, "level bit 1 -> D7");
  check_eq(fake::board.digital_out[8], 1, "level bit 2 -> D8");
  check_eq(fake::board.digital_out[12], 0, "level bit 3 -> D12");
  check_eq(fake::board.pwm[5], 10, "PWM 5 from our section");
  check_eq(fake::board.pwm[6], 20, "PWM 6 from our section");
  check_eq(fake::board.servo[9], 1000, "servo 9 from our section");
  link.now_us = 123456;
  check_eq(feed_count(link, bcast(9, {section(7, true, bcast_data(0x08, 11, 21, 1100))})), 1,
           "our section asks: one reply");
  r = link.replies.back();
  check_reply(r, wire::kBcast, 9, "BCAST_REPLY echoes the broadcast's seq");
  check_eq(r.size(), 9, "status, board time, one sample per input pin");
  check_eq(status_of(r), 0, "status");
  check_eq(u16(r, 7), 444, "A0 sampled");
  check_eq(fake::board.digital_out[12], 1, "applied with a reply too");
  check_eq(fake::board.servo[9], 1100, "servo");

  // Faulty broadcasts are dropped (RX_ERRORS), never answered with ERROR, nothing applied.
  const int pwm5 = fake::board.pwm[5];
  check_eq(feed_count(link, bcast(10, {section(7, true, Bytes{1, 2, 3})})), 0, "short section");
  check_eq(feed_count(link, bcast(11, {section(7, true, bcast_data(0, 1, 1, 499))})), 0,
           "servo value out of range");
  check_eq(feed_count(link, bcast(12, {Bytes{7, 0x85, 1, 2}})), 0, "section past the end");
  check_eq(feed_count(link, bcast(13, {Bytes{7, 0x45, 0, 1, 1, 0xE8, 3}})), 0,
           "reserved header bit");
  check_eq(feed_count(link, bcast(14, {section(7, true, bcast_data(0, 1, 1, 1000)), Bytes{9}})),
           0, "a well-formed section of ours in a frame whose tail is not: dropped whole");
  check_eq(fake::board.pwm[5], pwm5, "nothing applied from a faulty broadcast");
  r = link.request(tick(15, 0, 0));
  check_eq(status_of(r), wire::kStatusRxErrors, "the drops reported as RX_ERRORS");

  // Watchdog: a broadcast without our section does not feed it; one with ours does.
  link.request(tick(16, 0, 0, cat({pwm_write(5, 77)})));
  link.now_ms += 60;
  feed_count(link, bcast(17, {section(3, false, bcast_data(0, 1, 1, 1000))}));
  link.now_ms += 60;
  link.engine.poll(link.now_ms);
  check_eq(fake::board.pwm[5], 0, "others' broadcasts do not feed our watchdog: tripped");
  check_eq(fake::board.pwm[6], 3, "PWM 6 safe");
  feed_count(link, bcast(18, {section(7, false, bcast_data(0, 50, 51, 1000))}));
  check_eq(fake::board.pwm[5], 50, "a broadcast after a trip is applied");
  link.now_ms += 90;
  feed_count(link, bcast(19, {section(7, false, bcast_data(0, 52, 51, 1000))}));
  link.now_ms += 90;
  link.engine.poll(link.now_ms);
  check_eq(fake::board.pwm[5], 52, "our broadcasts feed the watchdog");
  check_eq(feed_count(link, bcast(20, {section(7, true, bcast_data(0, 53, 51, 1000))})), 1,
           "reply");
  check_eq(status_of(link.replies.back()), wire::kStatusWatchdogTripped,
           "the trip reported in the next reply");

  // E-stopped: writes ignored, samples still answered.
  link.request(estop(21));
  const long before_estop = fake::board.writes;
  check_eq(feed_count(link, bcast(22, {section(7, true, bcast_data(0x0F, 99, 99, 2000))})), 1,
           "answered while e-stopped");
  check(status_of(link.replies.back()) & wire::kStatusEstopped, "ESTOPPED reported");
  check_eq(fake::board.writes, before_estop, "writes ignored while e-stopped");
  // A CONFIG without the id takes the board out of broadcasts again.
  link.request(config(23, 100, kBcastBoard));
  check_eq(feed_count(link, bcast(24, {section(7, true, bcast_data(0, 1, 1, 1000))})), 0,
           "out of broadcasts after a CONFIG without id");
  check_eq(fake::board.violations, 0, "no illegal pin operation");
}

// ---------------------------------------------------------------- fuzz

Bytes random_request(test::Rng& rng, const hilswarm::Engine& engine) {
  const uint8_t seq = static_cast<uint8_t>(rng.next());
  const uint32_t kind = rng.below(100);
  if (kind < 25) {  // CONFIG, mostly plausible
    std::vector<Entry> entries;
    const uint32_t n = rng.below(rng.chance(10) ? 25 : 8);
    for (uint32_t i = 0; i < n; ++i) {
      Entry e;
      e.pin = static_cast<uint8_t>(rng.chance(90) ? 2 + rng.below(18) : rng.next());
      e.mode = static_cast<uint8_t>(rng.chance(90) ? rng.below(7) : rng.next());
      const uint8_t caps = hilswarm::pin_capabilities(e.pin);
      if (rng.chance(80) && !hilswarm::mode_allowed(e.mode, caps)) e.mode = wire::kModeDigitalOut;
      switch (e.mode) {
        case wire::kModeDigitalOut: e.safe = static_cast<uint16_t>(rng.below(rng.chance(95) ? 2 : 5)); break;
        case wire::kModePwm: e.safe = static_cast<uint16_t>(rng.below(rng.chance(95) ? 256 : 400)); break;
        case wire::kModeServo: e.safe = static_cast<uint16_t>(400 + rng.below(2200)); break;
        default: e.safe = static_cast<uint16_t>(rng.next());
      }
      entries.push_back(e);
    }
    Bytes p = config(seq, static_cast<uint16_t>(rng.chance(70) ? rng.below(300) : 0), entries);
    if (rng.chance(50)) p.push_back(static_cast<uint8_t>(rng.chance(90) ? 1 + rng.below(4) : 0));
    if (rng.chance(5)) p.resize(2 + rng.below(static_cast<uint32_t>(p.size())));
    return p;
  }
  if (kind < 35) {  // BCAST: sections of ids 1-4 (ours among them, mostly well-formed)
    Bytes p = {wire::kBcast, seq};
    const uint32_t n = 1 + rng.below(6);
    for (uint32_t i = 0; i < n; ++i) {
      const uint8_t id = static_cast<uint8_t>(1 + rng.below(4));
      uint8_t len = id == engine.bcast_id() && rng.chance(80) ? engine.section_length()
                                                               : static_cast<uint8_t>(rng.below(8));
      Bytes data(len);
      for (auto& b : data) b = static_cast<uint8_t>(rng.next());
      if (id == engine.bcast_id() && len == engine.section_length() && rng.chance(70)) {
        uint32_t n_out = 0;  // plausible servo values: after the levels, in pin order
        for (uint8_t pin = 0; pin < 20; ++pin) n_out += engine.pin(pin).mode == wire::kModeDigitalOut;
        uint32_t at_byte = (n_out + 7) / 8;
        for (uint8_t pin = 0; pin < 20 && at_byte < len; ++pin) {
          const uint8_t mode = engine.pin(pin).mode;
          if (mode == wire::kModePwm) ++at_byte;
          if (mode == wire::kModeServo && at_byte + 1 < len) {
            const uint16_t us = static_cast<uint16_t>(500 + rng.below(2001));
            data[at_byte] = static_cast<uint8_t>(us);
            data[at_byte + 1] = static_cast<uint8_t>(us >> 8);
            at_byte += 2;
          }
        }
      }
      uint8_t hdr = static_cast<uint8_t>(len | (rng.chance(40) ? wire::kBcastReplyFlag : 0));
      if (rng.chance(3)) hdr |= wire::kBcastReservedFlag;
      p.push_back(id);
      p.push_back(hdr);
      p.insert(p.end(), data.begin(), data.end());
    }
    if (rng.chance(5)) p.resize(2 + rng.below(static_cast<uint32_t>(p.size() - 1)));
    return p;
  }
  if (kind < 70) {  // TICK, mostly plausible for the current configuration
    uint32_t dout = 0, rmask = 0;
    Bytes writes;
    for (uint8_t pin = 0; pin < 20; ++pin) {
      const uint8_t mode = engine.pin(pin).mode;
      if (mode == wire::kModeDigitalOut && rng.chance(50)) dout |= 1u << pin;
      if (hilswarm::is_input_mode(mode) && rng.chance(60)) rmask |= 1u << pin;
      if (mode == wire::kModePwm && rng.chance(70)) {
        const Bytes w = pwm_write(pin, static_cast<uint8_t>(rng.next()));
        writes.insert(writes.end(), w.begin(), w.end());
      }
      if (mode == wire::kModeServo && rng.chance(70)) {
        const Bytes w = servo_write(pin, static_cast<uint16_t>(rng.chance(90) ? 500 + rng.below(2001)
                                                                              : rng.next()));
        writes.insert(writes.end(), w.begin(), w.end());
      }
    }
    if (rng.chance(5)) dout ^= 1u << rng.below(24);
    if (rng.chance(5)) rmask ^= 1u << rng.below(24);
    if (rng.chance(5)) writes.push_back(static_cast<uint8_t>(rng.below(24)));
    Bytes p = tick(seq, dout, rmask, writes);
    if (rng.chance(3)) p.resize(2 + rng.below(static_cast<uint32_t>(p.size() - 1)));
    return p;
  }
  if (kind < 80) {
    const uint8_t types[] = {wire::kHello, wire::kEstop, wire::kSetId};
    Bytes p = {types[rng.below(3)], seq};
    const uint32_t body = p[0] == wire::kSetId && rng.chance(80) ? 2 : (rng.chance(80) ? 0 : rng.below(4));
    for (uint32_t i = 0; i < body; ++i) p.push_back(static_cast<uint8_t>(rng.next()));
    return p;
  }
  // Anything: random type, random body (sometimes longer than the maximum payload).
  Bytes p = {static_cast<uint8_t>(rng.next()), seq};
  const uint32_t body = rng.below(rng.chance(10) ? 200 : 40);
  for (uint32_t i = 0; i < body; ++i) {
    p.push_back(static_cast<uint8_t>(rng.chance(20) ? 0 : rng.next()));
  }
  return p;
}

void test_fuzz(long frames, uint64_t seed) {
  const auto start = std::chrono::steady_clock::now();
  test::Rng rng(seed);
  fake::reset();
  test::Link link;
  link.boot();
  std::map<int, long> reply_types, error_codes;
  long clean = 0, mutated = 0, bytes = 0, bcast_frames = 0, bcast_replies = 0;
  for (long i = 0; i < frames; ++i) {
    link.now_ms += rng.below(rng.chance(2) ? 2000 : 40);
    link.now_us = static_cast<uint32_t>(rng.next());
    if (rng.chance(20)) link.engine.poll(link.now_ms);
    if (rng.chance(1)) {
      fake::reset(true);
      link.boot(rng.chance(50));
    }
    const Bytes payload = random_request(rng, link.engine);
    Bytes w = test::frame(payload);
    const bool mutate = rng.chance(15);
    if (mutate) {
      ++mutated;
      switch (rng.below(5)) {
        case 0: w[rng.below(static_cast<uint32_t>(w.size()))] ^= static_cast<uint8_t>(1u << rng.below(8)); break;
        case 1: w.erase(w.begin() + rng.below(static_cast<uint32_t>(w.size()))); break;
        case 2: {
          Bytes junk(rng.below(300));
          for (auto& b : junk) b = static_cast<uint8_t>(rng.chance(5) ? 0 : rng.next());
          w.insert(w.begin() + rng.below(static_cast<uint32_t>(w.size())), junk.begin(), junk.end());
          break;
        }
        case 3: w.resize(rng.below(static_cast<uint32_t>(w.size()))); break;
        default: w.insert(w.begin(), 0); break;
      }
      w.push_back(0);  // end the damage so the next clean frame starts fresh
    }
    const uint8_t estopped_before = link.engine.peek_status() & wire::kStatusEstopped;
    const size_t before = link.replies.size();
    link.feed(w);
    bytes += static_cast<long>(w.size());
    const size_t got = link.replies.size() - before;
    if (!mutate) {
      ++clean;
      const bool broadcast = payload.size() >= 2 && payload[0] == wire::kBcast &&
                             payload.size() <= wire::kMaxPayload;
      if (broadcast) {  // answered only when our section asks, never with ERROR
        ++bcast_frames;
        check(got <= 1, "BCAST gets at most one reply");
        if (got == 1) {
          ++bcast_replies;
          const Bytes& r = link.replies.back();
          check(at(r, 0) == (wire::kBcast | wire::kReplyBit) && at(r, 1) == payload[1],
                "BCAST_REPLY with the broadcast's seq");
        }
      } else {
        check(got == 1, "clean frame " + std::to_string(i) + " got " + std::to_string(got) +
                            " replies: " + test::to_hex(payload));
      }
      if (got == 1 && !broadcast) {
        const Bytes& r = link.replies.back();
        if (payload.size() > wire::kMaxPayload) {
          check(r.size() == 4 && at(r, 0) == wire::kError && at(r, 1) == 0 &&
                    at(r, 2) == wire::kErrFrameTooLong,
                "too-long frame gets FRAME_TOO_LONG with seq 0");
        } else {
          check(at(r, 1) == payload[1], "reply echoes seq");
          check(at(r, 0) == (payload[0] | wire::kReplyBit) || at(r, 0) == wire::kError,
                "reply type = request | 0x80 or ERROR");
          if (at(r, 0) == (wire::kTick | wire::kReplyBit) && !estopped_before) {
            const uint32_t dout = hilswarm::read_u24(&payload[2]);
            for (uint8_t pin = 0; pin < 20; ++pin) {
              if (link.engine.pin(pin).mode == wire::kModeDigitalOut) {
                check_eq(fake::board.digital_out[pin], (dout >> pin) & 1, "TICK applied dout");
              }
            }
          }
          if (at(r, 0) == (wire::kTick | wire::kReplyBit)) {
            const uint32_t rmask = hilswarm::read_u24(&payload[5]);
            check_eq(r.size(), 7 + 2 * __builtin_popcount(rmask), "one sample per rmask bit");
          }
        }
      }
    }
    for (size_t k = before; k < link.replies.size(); ++k) {
      const Bytes& r = link.replies[k];
      check(r.size() >= 2 && r.size() <= wire::kMaxPayload, "reply size");
      ++reply_types[at(r, 0)];
      if (at(r, 0) == wire::kError) {
        check(r.size() == 4 && at(r, 2) >= 1 && at(r, 2) <= 9, "ERROR code in range");
        ++error_codes[at(r, 2)];
      }
    }
    if (fake::board.violations != 0 || link.reply_framing_errors != 0) {
      check(false, "fuzz frame " + std::to_string(i) + ": " + fake::board.last_violation +
                       " (framing errors " + std::to_string(link.reply_framing_errors) + ")");
      break;
    }
  }
  const double secs =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::printf("fuzz: %ld frames (%ld clean, %ld damaged, %ld bytes), seed %llu, %.1f s\n", frames,
              clean, mutated, bytes, static_cast<unsigned long long>(seed), secs);
  std::printf("fuzz: replies by type:");
  for (const auto& kv : reply_types) std::printf(" 0x%02x=%ld", kv.first, kv.second);
  std::printf("\nfuzz: errors by code:");
  for (const auto& kv : error_codes) std::printf(" %d=%ld", kv.first, kv.second);
  std::printf("\n");
  check(error_codes.size() >= 7, "the fuzz loop reached most error codes");
  std::printf("fuzz: %ld clean BCAST frames, %ld answered\n", bcast_frames, bcast_replies);
  check(bcast_replies > 0 && bcast_frames > bcast_replies,
        "the fuzz loop produced answered and silent broadcasts");
  check(reply_types.count(wire::kTick | wire::kReplyBit) &&
            reply_types.count(wire::kConfig | wire::kReplyBit),
        "the fuzz loop produced accepted CONFIGs and TICKs");
}

}  // namespace

int main(int argc, char** argv) {
  std::string vectors;
  long fuzz_frames = 200000;
  uint64_t seed = 1;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    const char* v = i + 1 < argc ? argv[i + 1] : nullptr;
    if (a == "--vectors" && v) {
      vectors = v;
      ++i;
    } else if (a == "--fuzz-frames" && v) {
      fuzz_frames = std::atol(v);
      ++i;
    } else if (a == "--seed" && v) {
      seed = std::strtoull(v, nullptr, 10);
      ++i;
    } else {
      std::fprintf(stderr, "usage: %s --vectors PATH [--fuzz-frames N] [--seed S]\n", argv[0]);
      return 2;
    }
  }
  if (vectors.empty()) {
    std::fprintf(stderr, "test_protocol: --vectors PATH is required\n");
    return 2;
  }

  const std::vector<std::pair<const char*, std::function<void()>>> tests = {
      {"crc", test_crc},
      {"cobs", test_cobs},
      {"parser", test_parser},
      {"builder", test_builder},
      {"golden", [&] { test_golden(vectors); }},
      {"engine_boot_hello", test_engine_boot_and_hello},
      {"engine_config_errors", test_engine_config_errors},
      {"engine_config_tick", test_engine_config_and_tick},
      {"engine_estop", test_engine_estop},
      {"engine_watchdog", test_engine_watchdog},
      {"engine_rx_errors_id", test_engine_rx_errors_and_id},
      {"engine_broadcast", test_engine_broadcast},
      {"fuzz", [&] { test_fuzz(fuzz_frames, seed); }},
  };
  for (const auto& t : tests) {
    g_test = t.first;
    const long failures = g_failures;
    try {
      t.second();
    } catch (const std::exception& e) {
      check(false, std::string("exception: ") + e.what());
    }
    std::printf("%-22s %s\n", t.first, g_failures == failures ? "ok" : "FAILED");
  }
  std::printf("host-test: %ld checks, %ld failures\n", g_checks, g_failures);
  return g_failures == 0 ? 0 : 1;
}
