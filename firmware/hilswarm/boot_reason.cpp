#include "boot_reason.h"

#include <avr/io.h>
#include <avr/wdt.h>

// Not cleared by the C runtime (.noinit), written before .bss is cleared.
static uint8_t saved_reset_flags __attribute__((section(".noinit")));

// Runs in .init3: after the stack and __zero_reg__ are set up, before .data/.bss init and
// before any constructor. Naked: falls through to the next init section.
extern "C" void hilswarm_save_reset_flags(void) __attribute__((naked, used, section(".init3")));
extern "C" void hilswarm_save_reset_flags(void) {
  uint8_t flags = MCUSR;
  if (flags == 0) {
    // optiboot clears MCUSR before starting the sketch and leaves its old value in r2.
    __asm__ __volatile__("mov %0, r2" : "=r"(flags));
  }
  saved_reset_flags = flags;
  MCUSR = 0;
  wdt_disable();
}

namespace hilswarm {
namespace boot {

uint8_t reset_flags() { return saved_reset_flags; }

bool hw_watchdog_reset() { return (saved_reset_flags & _BV(WDRF)) != 0; }

}  // namespace boot
}  // namespace hilswarm
