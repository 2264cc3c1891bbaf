// Why the AVR booted: MCUSR is saved before anything else runs (section .init3), then cleared and
// the hardware watchdog disabled, so a watchdog reset cannot loop while the C runtime starts.
#ifndef HILSWARM_BOOT_REASON_H
#define HILSWARM_BOOT_REASON_H

#include <stdint.h>

namespace hilswarm {
namespace boot {

// MCUSR as found at reset (optiboot clears MCUSR and passes it in r2; that copy is used then).
uint8_t reset_flags();
// True if the last reset was caused by the AVR hardware watchdog (WDRF).
bool hw_watchdog_reset();

}  // namespace boot
}  // namespace hilswarm

#endif  // HILSWARM_BOOT_REASON_H
