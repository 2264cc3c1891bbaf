// libFuzzer target (optional, needs clang++: `make fuzz`): arbitrary bytes into the firmware's
// receive path (parser -> engine -> builder) with a fake board; the first byte picks the
// hardware-watchdog boot flag, time advances between bytes. Crashes, sanitizer reports, illegal
// pin operations and malformed replies abort.
#include <stdint.h>
#include <stdlib.h>

#include "fake_hal.h"
#include "test_support.h"
#include "wire.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size == 0) return 0;
  fake::reset();
  test::Link link;
  link.boot(data[0] & 1);
  for (size_t i = 1; i < size; ++i) {
    link.now_ms += data[i] & 7;
    link.now_us += 97;
    if ((data[i] & 0xF0) == 0xF0) link.engine.poll(link.now_ms);
    link.feed_byte(data[i]);
    if (fake::board.violations != 0 || link.reply_framing_errors != 0) abort();
  }
  for (const auto& r : link.replies) {
    if (r.size() < 2 || r.size() > hilswarm::wire::kMaxPayload) abort();
  }
  return 0;
}
