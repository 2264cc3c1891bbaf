// SPDX-License-Identifier: GPL-3.0-or-later
//
// hilswarm-simavr: runs the hilswarm firmware ELF in simavr, bridges the AVR's UART0 to a
// pseudo-terminal and serves a line-based control channel on stdin/stdout (README.md).
//
// This program links libsimavr (GPL-3.0-or-later), so the built binary is GPL-3.0-or-later
// (see LICENSE and NOTICE beside this file).
//
// Design:
// * One thread. The simulator runs in slices: --paced up to the wall clock (never ahead; steps
//   shorter than a UART byte time while bytes move), --unpaced 4000 cycles at a time; between
//   slices the harness polls the pty master and stdin, and --paced sleeps (ppoll, 1 us timer
//   slack) until the next step or wire event or until input arrives.
// * The wire is a real 8N1 line in simulated time (wire_byte_cycles(): 86.8 us per byte at
//   115200): simavr's UART byte time is set to it. Host -> AVR bytes are queued (never dropped)
//   with their arrival time and pushed into simavr's UART receive FIFO once simulated time has
//   reached it, while the receiver is enabled and the FIFO has room; simavr then hands them to
//   the firmware one byte time apart. AVR -> host bytes are delivered when their frame ends
//   (UDR0 write + one byte time, serialised) and written to the pty at once; while no host has
//   the pty open (POLLHUP on the master) they are discarded.
// * PWM duty and servo pulse widths are read from the timer registers (simavr does not model
//   Arduino's phase-correct PWM and misses OCR1x updates in Timer1 mode 14).

#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/prctl.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include <avr_adc.h>
#include <avr_extint.h>
#include <avr_ioport.h>
#include <avr_uart.h>
#include <sim_avr.h>
#include <sim_cycle_timers.h>
#include <sim_elf.h>
#include <sim_io.h>
#include <sim_irq.h>

// Accessors of simavr's UART FIFO (the header only declares its type).
DEFINE_FIFO(uint16_t, uart_fifo);

// ---------------------------------------------------------------- ATmega328P register map
// Data-space addresses (identical on ATmega48/88/168/328 and their P variants).
enum {
  REG_PINB = 0x23, REG_DDRB = 0x24, REG_PORTB = 0x25,
  REG_PINC = 0x26, REG_DDRC = 0x27, REG_PORTC = 0x28,
  REG_PIND = 0x29, REG_DDRD = 0x2A, REG_PORTD = 0x2B,
  REG_TCCR0A = 0x44, REG_OCR0A = 0x47, REG_OCR0B = 0x48,
  REG_TCCR1A = 0x80, REG_TCCR1B = 0x81,
  REG_ICR1L = 0x86, REG_OCR1AL = 0x88, REG_OCR1BL = 0x8A,
  REG_TCCR2A = 0xB0, REG_OCR2A = 0xB3, REG_OCR2B = 0xB4,
  REG_UCSR0A = 0xC0, REG_UCSR0B = 0xC1, REG_UCSR0C = 0xC2, REG_UBRR0L = 0xC4, REG_UBRR0H = 0xC5,
};
enum { BIT_COMA1 = 7, BIT_COMB1 = 5, BIT_RXEN0 = 4, BIT_U2X0 = 1 };

#define PIN_COUNT 20
#define ANALOG_PIN_BASE 14
#define UNPACED_SLICE_CYCLES 4000u         // --unpaced: poll the pty/stdin this often (sim)
#define PACED_IDLE_STEP_NS 1000000LL        // --paced, link idle: wake at least every 1 ms
#define PACED_ACTIVE_NS 5000000LL           // --paced: the link counts as active this long
                                            // after a byte moved (then: 0.9 byte time steps)
#define PACED_MIN_SLEEP_NS 2000LL           // --paced: shorter waits are run through
#define PACED_MAX_RUN_CYCLES 1600u          // --paced catch-up: poll every 100 us (sim)
#define PACED_MAX_LAG_NS 50000000LL         // --paced: a backlog beyond 50 ms is dropped
#define DISCONNECTED_RECHECK_NS 5000000LL   // poll a disconnected pty every 5 ms (wall)
#define QUEUE_LIMIT (1u << 20)              // 1 MiB per direction
#define LINE_MAX_LEN 256

static const char *const kUsage =
    "usage: hilswarm-simavr --elf PATH [--mcu atmega328p] [--freq 16000000]\n"
    "                       [--paced|--unpaced] [--vcc-mv 5000] [--aref-mv 5000]\n";

// ---------------------------------------------------------------- byte queue

typedef struct {
  uint8_t *buf;
  size_t cap, head, len;
} byte_queue_t;

static int queue_push(byte_queue_t *q, const uint8_t *data, size_t n) {
  if (q->len + n > q->cap) {
    size_t cap = q->cap ? q->cap : 4096;
    while (cap < q->len + n) cap *= 2;
    if (cap > QUEUE_LIMIT) return -1;
    uint8_t *buf = malloc(cap);
    if (!buf) return -1;
    for (size_t i = 0; i < q->len; ++i) buf[i] = q->buf[(q->head + i) % q->cap];
    free(q->buf);
    q->buf = buf;
    q->cap = cap;
    q->head = 0;
  }
  for (size_t i = 0; i < n; ++i) q->buf[(q->head + q->len + i) % q->cap] = data[i];
  q->len += n;
  return 0;
}

static uint8_t queue_pop(byte_queue_t *q) {
  uint8_t b = q->buf[q->head];
  q->head = (q->head + 1) % q->cap;
  q->len--;
  return b;
}

// Contiguous readable span at the head.
static size_t queue_span(const byte_queue_t *q, const uint8_t **data) {
  *data = q->buf + q->head;
  size_t end = q->head + q->len;
  return end <= q->cap ? q->len : q->cap - q->head;
}

static void queue_drop(byte_queue_t *q, size_t n) {
  q->head = (q->head + n) % (q->cap ? q->cap : 1);
  q->len -= n;
}

static void queue_clear(byte_queue_t *q) { q->head = q->len = 0; }

// ---------------------------------------------------------------- state

typedef struct {
  const char *elf;
  const char *mcu;
  uint32_t freq;
  int paced;
  uint32_t vcc_mv;
  uint32_t aref_mv;
} options_t;

static volatile sig_atomic_t g_stop = 0;
static avr_t *g_avr = NULL;
static avr_uart_t *g_uart = NULL;
static avr_irq_t *g_uart_in = NULL;
static byte_queue_t g_to_avr, g_to_host;
static int g_master = -1;
static int g_host_connected = 0;
static int g_muted = 0;  // fault injection: the firmware's replies are lost on the way to the host
static FILE *g_ctl = NULL;  // the control channel (original stdout)
static uint64_t g_cycle_offset = 0;  // keeps simulated time monotonic across AVR resets
static uint64_t g_last_cycle = 0;
static int g_paced = 1;
static int64_t g_ref_ns = 0;      // --paced: wall-clock time at which simulated time was ...
static uint64_t g_ref_cycle = 0;  // ... this cycle (sim_cycles())
static uint64_t g_last_byte_cycle = 0;  // sim_cycles() when a byte last moved on the wire

static void on_signal(int sig) {
  (void)sig;
  g_stop = 1;
}

static int64_t monotonic_ns(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static void logger(avr_t *avr, const int level, const char *format, va_list ap) {
  (void)avr;
  (void)level;
  vfprintf(stderr, format, ap);
}

// Simulated cycles since start, monotonic even if the AVR core restarts its counter.
static uint64_t sim_cycles(void) {
  uint64_t c = g_avr->cycle;
  if (c < g_last_cycle) g_cycle_offset += g_last_cycle - c;
  g_last_cycle = c;
  return c + g_cycle_offset;
}

// --paced: the simulated cycle that corresponds to wall-clock time now_ns.
static uint64_t cycles_at(int64_t now_ns) {
  if (now_ns <= g_ref_ns) return g_ref_cycle;
  const unsigned __int128 elapsed =
      (unsigned __int128)(uint64_t)(now_ns - g_ref_ns) * g_avr->frequency;
  return g_ref_cycle + (uint64_t)(elapsed / 1000000000u);
}

// ---------------------------------------------------------------- wire timing
//
// One byte on the simulated wire takes wire_byte_cycles() of simulated time: its frame bits
// (start + data + parity + stop, from UCSR0B/C) at the slower of the AVR's real baud rate
// (from UBRR0 and U2X0) and the standard rate it approximates (the host's USB-serial adapter
// runs at exactly 115200 while a 16 MHz AVR runs at 117647). 115200 8N1 at 16 MHz: 1389 cycles,
// 86.8 us. simavr 1.6 would count an 11-bit frame (it always adds a parity bit): 93.5 us.

static const uint32_t kStandardBauds[] = {300,    600,    1200,   2400,   4800,   9600,
                                          14400,  19200,  28800,  38400,  57600,  76800,
                                          115200, 230400, 250000, 460800, 500000, 921600,
                                          1000000, 2000000};

static uint64_t wire_byte_cycles(void) {
  const uint8_t *d = g_avr->data;
  static const uint8_t kDataBits[8] = {5, 6, 7, 8, 8, 8, 8, 9};
  const unsigned ucsz = ((d[REG_UCSR0C] >> 1) & 3u) | (((d[REG_UCSR0B] >> 2) & 1u) << 2);
  const uint64_t frame_bits = 1u + kDataBits[ucsz] + (((d[REG_UCSR0C] >> 4) & 3u) ? 1u : 0u) +
                              (((d[REG_UCSR0C] >> 3) & 1u) ? 2u : 1u);
  const uint64_t ubrr = (((unsigned)d[REG_UBRR0H] & 0x0Fu) << 8) | d[REG_UBRR0L];
  const uint64_t bit_cycles = (ubrr + 1) * (((d[REG_UCSR0A] >> BIT_U2X0) & 1u) ? 8u : 16u);
  const uint64_t avr_byte = frame_bits * bit_cycles;
  const double avr_baud = (double)g_avr->frequency / (double)bit_cycles;
  uint64_t nominal = 0;
  double best = 0.05;  // a standard rate within 5 % is what the other end of the wire runs at
  for (size_t i = 0; i < sizeof(kStandardBauds) / sizeof(kStandardBauds[0]); ++i) {
    const double error = avr_baud / kStandardBauds[i] - 1.0;
    if (error < best && error > -best) {
      best = error < 0 ? -error : error;
      nominal = kStandardBauds[i];
    }
  }
  if (!nominal) return avr_byte;
  const uint64_t host_byte = (frame_bits * g_avr->frequency + nominal - 1) / nominal;
  return host_byte > avr_byte ? host_byte : avr_byte;
}

// simavr paces its UART with cycles_per_byte (RX: RXC raised that long after a byte enters an
// idle receiver, then once per byte while its FIFO holds more; TX: UDRE/TXC that long after a
// UDR write). The firmware (re)configures the baud rate at any time, so this runs before every
// use.
static uint64_t sync_wire_timing(void) {
  const uint64_t cycles = wire_byte_cycles();
  if (g_uart->cycles_per_byte != cycles) g_uart->cycles_per_byte = cycles;
  return cycles;
}

// ---------------------------------------------------------------- trace (diagnostics)

static FILE *g_trace = NULL;  // HILSWARM_SIMAVR_TRACE=1: timing events on stderr
#define TRACE(kind, fmt, ...)                                                          \
  do {                                                                                 \
    if (g_trace) {                                                                     \
      fprintf(g_trace, "%s %llu %lld " fmt "\n", kind, (unsigned long long)sim_cycles(), \
              (long long)monotonic_ns(), __VA_ARGS__);                                  \
    }                                                                                  \
  } while (0)

// Polls simavr's receive FIFO every 64 cycles (4 us at 16 MHz) to log when the firmware reads
// a byte.
static avr_cycle_count_t trace_rx_reads(struct avr_t *avr, avr_cycle_count_t when, void *param) {
  (void)avr;
  (void)param;
  static unsigned previous = 0;
  const unsigned held = uart_fifo_get_read_size(&g_uart->input);
  if (held < previous) TRACE("rxread", "%u", previous - held);
  previous = held;
  return when + 64;
}

// ---------------------------------------------------------------- UART bridge

static int uart_rx_enabled(void) { return (g_avr->data[REG_UCSR0B] >> BIT_RXEN0) & 1; }

// A host byte may not enter the wire before it reached the harness: every chunk read from the
// pty carries the simulated cycle of its arrival (--paced: the cycle matching the wall-clock
// time of the read, so a simulation that lags behind the wall clock and catches up cannot
// answer sooner than a real board would).
#define ARRIVAL_CAPACITY 4096u
static struct {
  size_t bytes[ARRIVAL_CAPACITY];  // bytes of g_to_avr that arrived together
  uint64_t ready[ARRIVAL_CAPACITY];  // sim_cycles() at which they arrived
  size_t head, len;
} g_arrivals;

static void note_arrival(size_t n) {
  const uint64_t now = sim_cycles();
  uint64_t ready = g_paced ? cycles_at(monotonic_ns()) : now;
  if (ready < now) ready = now;
  if (g_arrivals.len == ARRIVAL_CAPACITY) {  // merge into the newest chunk (only later)
    const size_t last = (g_arrivals.head + g_arrivals.len - 1) % ARRIVAL_CAPACITY;
    g_arrivals.bytes[last] += n;
    g_arrivals.ready[last] = ready;
    return;
  }
  const size_t slot = (g_arrivals.head + g_arrivals.len) % ARRIVAL_CAPACITY;
  g_arrivals.bytes[slot] = n;
  g_arrivals.ready[slot] = ready;
  g_arrivals.len++;
}

static void feed_avr(void);

static avr_cycle_count_t feed_later(struct avr_t *avr, avr_cycle_count_t when, void *param) {
  (void)avr;
  (void)when;
  (void)param;
  feed_avr();
  return 0;
}

// Moves queued host bytes that have arrived into simavr's UART receive FIFO while it has room.
// A byte entering the FIFO starts its frame on the wire: simavr hands it to the firmware one
// byte time later and every further byte one byte time after the previous one, so the FIFO is
// the wire.
static void feed_avr(void) {
  if (g_to_avr.len == 0 || !uart_rx_enabled()) return;
  sync_wire_timing();
  while (g_to_avr.len > 0 && uart_rx_enabled() && !uart_fifo_isfull(&g_uart->input)) {
    const uint64_t now = sim_cycles();
    if (g_arrivals.ready[g_arrivals.head] > now) {  // not there yet: feed when it is
      avr_cycle_timer_cancel(g_avr, feed_later, NULL);
      avr_cycle_timer_register(g_avr, g_arrivals.ready[g_arrivals.head] - now, feed_later,
                               NULL);
      return;
    }
    if (--g_arrivals.bytes[g_arrivals.head] == 0) {
      g_arrivals.head = (g_arrivals.head + 1) % ARRIVAL_CAPACITY;
      g_arrivals.len--;
    }
    const uint8_t b = queue_pop(&g_to_avr);
    g_last_byte_cycle = now;
    TRACE("rxfeed", "%u", (unsigned)b);
    avr_raise_irq(g_uart_in, b);
  }
}

static void on_uart_xon(struct avr_irq_t *irq, uint32_t value, void *param) {
  (void)irq;
  (void)value;
  (void)param;
  feed_avr();
}

// AVR -> host: simavr reports a byte when the firmware writes UDR0, i.e. when its frame starts.
// The host gets it when the frame ends: one byte time after the line is free for it.
#define TX_WIRE_CAPACITY 1024u
static struct {
  uint8_t byte[TX_WIRE_CAPACITY];
  avr_cycle_count_t due[TX_WIRE_CAPACITY];  // simavr cycle at which the stop bit ends
  size_t head, len;
  avr_cycle_count_t line_free;  // end of the last frame on the wire
  int armed;                    // tx_deliver is registered
} g_tx;

static void flush_to_host(void);

static avr_cycle_count_t tx_deliver(struct avr_t *avr, avr_cycle_count_t when, void *param) {
  (void)avr;
  (void)param;
  while (g_tx.len > 0 && g_tx.due[g_tx.head] <= when) {
    const uint8_t b = g_tx.byte[g_tx.head];
    g_tx.head = (g_tx.head + 1) % TX_WIRE_CAPACITY;
    g_tx.len--;
    TRACE("deliver", "%u", (unsigned)b);
    if (!g_host_connected) continue;  // nobody listening: a later host must not read stale bytes
    if (g_muted) continue;            // a broken TX line: the host never sees this byte
    if (queue_push(&g_to_host, &b, 1) != 0) {
      fprintf(stderr, "hilswarm-simavr: host is not reading the pty; output queue full\n");
      queue_clear(&g_to_host);
    }
  }
  flush_to_host();
  if (g_tx.len > 0) return g_tx.due[g_tx.head];
  g_tx.armed = 0;
  return 0;
}

// An AVR reset (watchdog) cancels every cycle timer: bytes still on the wire are cut off.
static void tx_check_reset(void) {
  if (g_tx.len == 0) return;
  if (avr_cycle_timer_status(g_avr, tx_deliver, NULL) == 0 &&
      g_tx.due[g_tx.head] > g_avr->cycle) {
    g_tx.len = 0;
    g_tx.armed = 0;
    g_tx.line_free = 0;
  }
}

static void on_uart_output(struct avr_irq_t *irq, uint32_t value, void *param) {
  (void)irq;
  (void)param;
  tx_check_reset();
  const uint64_t byte_cycles = sync_wire_timing();  // before simavr starts its TX pump
  const avr_cycle_count_t now = g_avr->cycle;
  if (g_tx.line_free < now || g_tx.line_free > now + TX_WIRE_CAPACITY * byte_cycles) {
    g_tx.line_free = now;  // idle line (or a cycle counter that restarted)
  }
  if (g_tx.len == TX_WIRE_CAPACITY) {  // the firmware ignores UDRE: a real UART loses bytes too
    fprintf(stderr, "hilswarm-simavr: UART transmit overrun; byte dropped\n");
    return;
  }
  g_tx.line_free += byte_cycles;
  const size_t slot = (g_tx.head + g_tx.len) % TX_WIRE_CAPACITY;
  g_tx.byte[slot] = (uint8_t)value;
  g_tx.due[slot] = g_tx.line_free;
  g_tx.len++;
  g_last_byte_cycle = sim_cycles();
  TRACE("tx", "%u", (unsigned)value);
  if (!g_tx.armed) {
    avr_cycle_timer_register(g_avr, g_tx.line_free - now, tx_deliver, NULL);
    g_tx.armed = 1;
  }
}

static void flush_to_host(void) {
  while (g_host_connected && g_to_host.len > 0) {
    const uint8_t *data;
    size_t n = queue_span(&g_to_host, &data);
    ssize_t w = write(g_master, data, n);
    if (w > 0) {
      TRACE("hostout", "%zd", w);
      queue_drop(&g_to_host, (size_t)w);
    } else {
      if (w < 0 && errno == EIO) {
        g_host_connected = 0;
        queue_clear(&g_to_host);
      }
      return;  // EAGAIN: the pty buffer is full, retry on the next pass
    }
  }
}

static void read_from_host(void) {
  uint8_t buf[4096];
  for (;;) {
    if (g_to_avr.len + sizeof(buf) > QUEUE_LIMIT) return;  // back-pressure: leave it in the pty
    ssize_t n = read(g_master, buf, sizeof(buf));
    if (n > 0) {
      TRACE("hostin", "%zd", n);
      if (queue_push(&g_to_avr, buf, (size_t)n) != 0) return;
      note_arrival((size_t)n);
      continue;
    }
    if (n < 0 && errno == EIO) g_host_connected = 0;
    return;
  }
}

// Connection state of the pty: POLLHUP on the master while no process has the slave open.
static void check_host(short revents) {
  int connected = !(revents & POLLHUP);
  if (connected && !g_host_connected) queue_clear(&g_to_host);
  g_host_connected = connected;
}

static int open_pty(char *slave_name, size_t len) {
  int fd = posix_openpt(O_RDWR | O_NOCTTY);
  if (fd < 0 || grantpt(fd) != 0 || unlockpt(fd) != 0) return -1;
  if (ptsname_r(fd, slave_name, len) != 0) return -1;
  struct termios tio;
  if (tcgetattr(fd, &tio) != 0) return -1;
  cfmakeraw(&tio);
  tio.c_cc[VMIN] = 1;
  tio.c_cc[VTIME] = 0;
  if (tcsetattr(fd, TCSANOW, &tio) != 0) return -1;
  int flags = fcntl(fd, F_GETFL);
  if (flags < 0 || fcntl(fd, F_SETFL, flags | O_NONBLOCK) != 0) return -1;
  return fd;
}

// ---------------------------------------------------------------- control channel

static void reply(const char *fmt, ...) {
  va_list ap;
  va_start(ap, fmt);
  vfprintf(g_ctl, fmt, ap);
  va_end(ap);
  fputc('\n', g_ctl);
  fflush(g_ctl);
}

#define FAIL_REPLY(...) \
  do {                     \
    reply(__VA_ARGS__);    \
    return;                \
  } while (0)

static int parse_uint(const char *s, unsigned long max, unsigned long *out) {
  if (!s || !*s) return -1;
  char *end = NULL;
  errno = 0;
  unsigned long v = strtoul(s, &end, 10);
  if (errno || *end || s[0] == '-' || s[0] == '+' || v > max) return -1;
  *out = v;
  return 0;
}

// Port register addresses and bit of an Arduino pin (0-7 PORTD, 8-13 PORTB, 14-19 PORTC).
static void pin_port(int pin, char *port, int *ddr, int *portreg, int *bit) {
  if (pin < 8) {
    *port = 'D'; *ddr = REG_DDRD; *portreg = REG_PORTD; *bit = pin;
  } else if (pin < 14) {
    *port = 'B'; *ddr = REG_DDRB; *portreg = REG_PORTB; *bit = pin - 8;
  } else {
    *port = 'C'; *ddr = REG_DDRC; *portreg = REG_PORTC; *bit = pin - 14;
  }
}

static unsigned reg16(int low_address) {
  return g_avr->data[low_address] | ((unsigned)g_avr->data[low_address + 1] << 8);
}

static void cmd_state(void) {
  const uint8_t *d = g_avr->data;
  char out[1024];
  size_t n = 0;
  uint64_t t_us = sim_cycles() * 1000000ULL / g_avr->frequency;
  n += snprintf(out + n, sizeof(out) - n, "{\"t_us\": %llu, \"digital\": [",
                (unsigned long long)t_us);
  for (int pin = 0; pin < PIN_COUNT; ++pin) {
    char port;
    int ddr, portreg, bit;
    pin_port(pin, &port, &ddr, &portreg, &bit);
    int level = (d[ddr] >> bit) & 1 ? (d[portreg] >> bit) & 1 : -1;
    n += snprintf(out + n, sizeof(out) - n, "%s%d", pin ? ", " : "", level);
  }
  n += snprintf(out + n, sizeof(out) - n, "], \"pwm\": {");

  int first = 1;
#define PWM_ENTRY(pin, value)                                                           \
  do {                                                                                  \
    n += snprintf(out + n, sizeof(out) - n, "%s\"%d\": %u", first ? "" : ", ", (pin), \
                  (unsigned)(value));                                                   \
    first = 0;                                                                          \
  } while (0)
  // Ascending pin order: 3 (OC2B), 5 (OC0B), 6 (OC0A), 9 (OC1A), 10 (OC1B), 11 (OC2A).
  const unsigned wgm1 = (d[REG_TCCR1A] & 3u) | (((d[REG_TCCR1B] >> 3) & 3u) << 2);
  const unsigned cs1 = d[REG_TCCR1B] & 7u;
  const int servo_mode = wgm1 == 14;
  if (d[REG_TCCR2A] & (1u << BIT_COMB1)) PWM_ENTRY(3, d[REG_OCR2B]);
  if (d[REG_TCCR0A] & (1u << BIT_COMB1)) PWM_ENTRY(5, d[REG_OCR0B]);
  if (d[REG_TCCR0A] & (1u << BIT_COMA1)) PWM_ENTRY(6, d[REG_OCR0A]);
  if (!servo_mode) {
    unsigned a = reg16(REG_OCR1AL), b = reg16(REG_OCR1BL);
    if (d[REG_TCCR1A] & (1u << BIT_COMA1)) PWM_ENTRY(9, a > 255 ? 255 : a);
    if (d[REG_TCCR1A] & (1u << BIT_COMB1)) PWM_ENTRY(10, b > 255 ? 255 : b);
  }
  if (d[REG_TCCR2A] & (1u << BIT_COMA1)) PWM_ENTRY(11, d[REG_OCR2A]);
  n += snprintf(out + n, sizeof(out) - n, "}, \"servo\": {");

  first = 1;
  static const unsigned kPrescaler[8] = {0, 1, 8, 64, 256, 1024, 0, 0};
  if (servo_mode && kPrescaler[cs1]) {
    const uint64_t scale = (uint64_t)kPrescaler[cs1] * 1000000ULL;
    const uint64_t freq = g_avr->frequency;
    if (d[REG_TCCR1A] & (1u << BIT_COMA1)) {
      PWM_ENTRY(9, ((reg16(REG_OCR1AL) + 1ULL) * scale + freq / 2) / freq);
    }
    if (d[REG_TCCR1A] & (1u << BIT_COMB1)) {
      PWM_ENTRY(10, ((reg16(REG_OCR1BL) + 1ULL) * scale + freq / 2) / freq);
    }
  }
#undef PWM_ENTRY
  n += snprintf(out + n, sizeof(out) - n, "}}");
  reply("%s", out);
}

static void cmd_adc(char *pin_s, char *mv_s) {
  unsigned long pin, mv;
  if (!pin_s || !mv_s) FAIL_REPLY("err adc: usage 'adc <pin 14-19> <millivolts>'");
  if (parse_uint(pin_s, 19, &pin) != 0 || pin < ANALOG_PIN_BASE) {
    FAIL_REPLY("err adc: pin must be 14-19");
  }
  if (parse_uint(mv_s, 65535, &mv) != 0) {
    FAIL_REPLY("err adc: millivolts must be an integer 0-65535");
  }
  avr_irq_t *irq = avr_io_getirq(g_avr, AVR_IOCTL_ADC_GETIRQ,
                                 ADC_IRQ_ADC0 + (int)(pin - ANALOG_PIN_BASE));
  if (!irq) FAIL_REPLY("err adc: this MCU has no ADC input %lu", pin - ANALOG_PIN_BASE);
  avr_raise_irq(irq, (uint32_t)mv);
  reply("ok");
}

static void cmd_din(char *pin_s, char *level_s) {
  unsigned long pin, level;
  if (!pin_s || !level_s) FAIL_REPLY("err din: usage 'din <pin 2-19> <0|1>'");
  if (parse_uint(pin_s, 19, &pin) != 0 || pin < 2) FAIL_REPLY("err din: pin must be 2-19");
  if (parse_uint(level_s, 1, &level) != 0) FAIL_REPLY("err din: level must be 0 or 1");
  char port;
  int ddr, portreg, bit;
  pin_port((int)pin, &port, &ddr, &portreg, &bit);
  avr_irq_t *irq = avr_io_getirq(g_avr, AVR_IOCTL_IOPORT_GETIRQ(port), bit);
  if (!irq) FAIL_REPLY("err din: no port %c on this MCU", port);
  avr_raise_irq(irq, (uint32_t)level);
  reply("ok");
}

// Executes one control line; returns 1 if the harness must quit.
static int run_command(char *line) {
  size_t len = strlen(line);
  while (len > 0 && (line[len - 1] == '\r' || line[len - 1] == ' ')) line[--len] = '\0';
  char *save = NULL;
  char *cmd = strtok_r(line, " \t", &save);
  if (!cmd) return 0;  // empty line: no reply
  char *a1 = strtok_r(NULL, " \t", &save);
  char *a2 = strtok_r(NULL, " \t", &save);
  char *extra = strtok_r(NULL, " \t", &save);
  if (strcmp(cmd, "state") == 0 && !a1) {
    cmd_state();
  } else if (strcmp(cmd, "adc") == 0 && !extra) {
    cmd_adc(a1, a2);
  } else if (strcmp(cmd, "din") == 0 && !extra) {
    cmd_din(a1, a2);
  } else if (strcmp(cmd, "ping") == 0 && !a1) {
    reply("ok");
  } else if (strcmp(cmd, "mute") == 0 && a1 && !a2) {
    if (strcmp(a1, "0") != 0 && strcmp(a1, "1") != 0) {
      reply("err mute: expected 0 or 1");
    } else {
      g_muted = a1[0] == '1';
      reply("ok");
    }
  } else if (strcmp(cmd, "quit") == 0 && !a1) {
    reply("ok");
    return 1;
  } else if (strcmp(cmd, "state") == 0 || strcmp(cmd, "adc") == 0 || strcmp(cmd, "din") == 0 ||
             strcmp(cmd, "ping") == 0 || strcmp(cmd, "quit") == 0 || strcmp(cmd, "mute") == 0) {
    reply("err %s: wrong number of arguments", cmd);
  } else {
    reply("err unknown command '%.40s'", cmd);
  }
  return 0;
}

// Reads available stdin; runs complete lines. Returns 1 to quit (command or EOF).
static int read_control(void) {
  static char line[LINE_MAX_LEN + 1];
  static size_t len = 0;
  static int overlong = 0;
  char buf[1024];
  ssize_t n = read(STDIN_FILENO, buf, sizeof(buf));
  if (n == 0) return 1;  // EOF
  if (n < 0) return (errno == EAGAIN || errno == EINTR) ? 0 : 1;
  for (ssize_t i = 0; i < n; ++i) {
    if (buf[i] == '\n') {
      line[len] = '\0';
      if (overlong) {
        reply("err line longer than %d characters", LINE_MAX_LEN);
      } else if (run_command(line)) {
        return 1;
      }
      len = 0;
      overlong = 0;
    } else if (len < LINE_MAX_LEN) {
      line[len++] = buf[i];
    } else {
      overlong = 1;
    }
  }
  return 0;
}

// ---------------------------------------------------------------- set-up

static int parse_options(int argc, char **argv, options_t *o) {
  o->elf = NULL;
  o->mcu = "atmega328p";
  o->freq = 16000000;
  o->paced = 1;
  o->vcc_mv = 5000;
  o->aref_mv = 5000;
  for (int i = 1; i < argc; ++i) {
    const char *a = argv[i];
    const char *v = i + 1 < argc ? argv[i + 1] : NULL;
    unsigned long x;
    if (strcmp(a, "--help") == 0 || strcmp(a, "-h") == 0) {
      fputs(kUsage, stdout);
      exit(0);
    } else if (strcmp(a, "--paced") == 0) {
      o->paced = 1;
    } else if (strcmp(a, "--unpaced") == 0) {
      o->paced = 0;
    } else if (strcmp(a, "--elf") == 0 && v) {
      o->elf = v;
      ++i;
    } else if (strcmp(a, "--mcu") == 0 && v) {
      o->mcu = v;
      ++i;
    } else if (strcmp(a, "--freq") == 0 && v && parse_uint(v, 40000000, &x) == 0 && x > 0) {
      o->freq = (uint32_t)x;
      ++i;
    } else if (strcmp(a, "--vcc-mv") == 0 && v && parse_uint(v, 6000, &x) == 0 && x > 0) {
      o->vcc_mv = (uint32_t)x;
      ++i;
    } else if (strcmp(a, "--aref-mv") == 0 && v && parse_uint(v, 6000, &x) == 0 && x > 0) {
      o->aref_mv = (uint32_t)x;
      ++i;
    } else {
      fprintf(stderr, "hilswarm-simavr: bad or incomplete option '%s'\n%s", a, kUsage);
      return -1;
    }
  }
  if (!o->elf) {
    fprintf(stderr, "hilswarm-simavr: --elf PATH is required\n%s", kUsage);
    return -1;
  }
  static const char *const kSupported[] = {"atmega328p", "atmega328", "atmega168p",
                                           "atmega168", "atmega88p", "atmega88"};
  for (size_t i = 0; i < sizeof(kSupported) / sizeof(kSupported[0]); ++i) {
    if (strcmp(o->mcu, kSupported[i]) == 0) return 0;
  }
  fprintf(stderr, "hilswarm-simavr: --mcu %s is not an ATmega48/88/168/328-family part\n",
          o->mcu);
  return -1;
}

static avr_uart_t *find_uart0(avr_t *avr) {
  for (avr_io_t *io = avr->io_port; io; io = io->next) {
    if (io->kind && strcmp(io->kind, "uart") == 0 && ((avr_uart_t *)io)->name == '0') {
      return (avr_uart_t *)io;
    }
  }
  return NULL;
}

static int setup_avr(const options_t *o) {
  elf_firmware_t fw;
  memset(&fw, 0, sizeof(fw));
  if (elf_read_firmware(o->elf, &fw) != 0) {
    fprintf(stderr, "hilswarm-simavr: cannot load ELF '%s'\n", o->elf);
    return -1;
  }
  snprintf(fw.mmcu, sizeof(fw.mmcu), "%s", o->mcu);
  fw.frequency = o->freq;
  fw.vcc = o->vcc_mv;
  fw.avcc = o->vcc_mv;
  fw.aref = o->aref_mv;
  g_avr = avr_make_mcu_by_name(o->mcu);
  if (!g_avr) {
    fprintf(stderr, "hilswarm-simavr: simavr has no core '%s'\n", o->mcu);
    return -1;
  }
  avr_init(g_avr);
  g_avr->log = LOG_ERROR;
  avr_load_firmware(g_avr, &fw);
  g_avr->frequency = o->freq;
  g_avr->vcc = o->vcc_mv;
  g_avr->avcc = o->vcc_mv;
  g_avr->aref = o->aref_mv;

  // simavr 1.6 re-triggers INT0/INT1 every cycle while D2/D3 are low unless this is off.
  avr_extint_set_strict_lvl_trig(g_avr, 0, 0);
  avr_extint_set_strict_lvl_trig(g_avr, 1, 0);

  g_uart = find_uart0(g_avr);
  if (!g_uart) {
    fprintf(stderr, "hilswarm-simavr: core '%s' has no UART0\n", o->mcu);
    return -1;
  }
  uint32_t flags = 0;  // no stdio echo of UART output, no usleep() when polling UCSRA
  avr_ioctl(g_avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
  g_uart_in = avr_io_getirq(g_avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
  avr_irq_register_notify(avr_io_getirq(g_avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT),
                          on_uart_output, NULL);
  avr_irq_register_notify(avr_io_getirq(g_avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XON),
                          on_uart_xon, NULL);
  return 0;
}

// ---------------------------------------------------------------- main loop

int main(int argc, char **argv) {
  options_t opt;
  if (parse_options(argc, argv, &opt) != 0) return 2;

  // The control channel keeps the real stdout; anything else printing to stdout (libsimavr)
  // lands on stderr instead.
  // (Before anything is printed on stderr: tracing makes it fully buffered.)
  int ctl_fd = dup(STDOUT_FILENO);
  if (ctl_fd < 0 || dup2(STDERR_FILENO, STDOUT_FILENO) < 0 || !(g_ctl = fdopen(ctl_fd, "w"))) {
    perror("hilswarm-simavr: stdout");
    return 1;
  }
  avr_global_logger_set(logger);

  struct sigaction sa;
  memset(&sa, 0, sizeof(sa));
  sa.sa_handler = on_signal;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGTERM, &sa, NULL);
  sigaction(SIGINT, &sa, NULL);
  signal(SIGPIPE, SIG_IGN);

  if (getenv("HILSWARM_SIMAVR_TRACE")) {
    static char trace_buffer[1 << 16];  // buffered: tracing must not slow the bridge much
    setvbuf(stderr, trace_buffer, _IOFBF, sizeof(trace_buffer));
    g_trace = stderr;
  }
  if (setup_avr(&opt) != 0) return 1;
  if (g_trace) avr_cycle_timer_register(g_avr, 64, trace_rx_reads, NULL);
  char slave[128];
  g_master = open_pty(slave, sizeof(slave));
  if (g_master < 0) {
    perror("hilswarm-simavr: pty");
    return 1;
  }
  int in_flags = fcntl(STDIN_FILENO, F_GETFL);
  if (in_flags >= 0) fcntl(STDIN_FILENO, F_SETFL, in_flags | O_NONBLOCK);

  reply("PTY %s", slave);

  // Paced mode sleeps in steps of tens of microseconds: ask for a precise timer (default
  // slack is 50 us).
  prctl(PR_SET_TIMERSLACK, 1000UL, 0, 0, 0);

  g_paced = opt.paced;
  g_ref_ns = monotonic_ns();
  g_ref_cycle = sim_cycles();
  const uint64_t freq = g_avr->frequency;
  const uint64_t max_lag_cycles = (uint64_t)PACED_MAX_LAG_NS * freq / 1000000000ULL;
  const uint64_t active_cycles = (uint64_t)PACED_ACTIVE_NS * freq / 1000000000ULL;
  int64_t next_hup_check_ns = 0;
  int exit_code = 0;
  while (!g_stop) {
    // 1. Run the AVR: up to the wall clock (paced; never ahead of it) or one slice (unpaced).
    uint64_t target;
    const uint64_t cur = sim_cycles();
    if (opt.paced) {
      target = cycles_at(monotonic_ns());
      if (target > cur + max_lag_cycles) {  // the harness was stalled: drop the backlog
        const uint64_t dropped = target - cur - max_lag_cycles;
        g_ref_ns += (int64_t)(dropped * 1000000000ULL / freq);
        for (size_t i = 0; i < g_arrivals.len; ++i) {  // host bytes keep their place in time
          uint64_t *ready = &g_arrivals.ready[(g_arrivals.head + i) % ARRIVAL_CAPACITY];
          *ready = *ready > cur + dropped ? *ready - dropped : cur;
        }
        target = cycles_at(monotonic_ns());
      }
      if (target > cur + PACED_MAX_RUN_CYCLES) target = cur + PACED_MAX_RUN_CYCLES;
    } else {
      target = cur + UNPACED_SLICE_CYCLES;
    }
    while (sim_cycles() < target) {
      int state = avr_run(g_avr);
      if (state == cpu_Done || state == cpu_Crashed) {
        fprintf(stderr, "hilswarm-simavr: simulated CPU %s at pc=0x%04x\n",
                state == cpu_Done ? "stopped (sleep with interrupts off)" : "crashed",
                (unsigned)g_avr->pc);
        exit_code = 1;
        goto done;
      }
    }
    tx_check_reset();
    sync_wire_timing();

    // 2. Exchange bytes and commands at the current simulated time (host bytes read now are
    // stamped with their arrival time; commands see the AVR as of now).
    const int64_t now_ns = monotonic_ns();
    struct pollfd fds[2] = {{STDIN_FILENO, POLLIN, 0}, {g_master, 0, 0}};
    const int watch_master = g_host_connected || now_ns >= next_hup_check_ns;
    if (watch_master) fds[1].events = POLLIN | (g_to_host.len ? POLLOUT : 0);
    const struct timespec zero = {0, 0};
    int ready = ppoll(fds, watch_master ? 2 : 1, &zero, NULL);
    if (ready < 0 && errno != EINTR) {
      perror("hilswarm-simavr: ppoll");
      exit_code = 1;
      break;
    }
    if (ready < 0) continue;  // EINTR
    if (watch_master) {
      check_host(fds[1].revents);
      if (!g_host_connected) next_hup_check_ns = now_ns + DISCONNECTED_RECHECK_NS;
      if (fds[1].revents & POLLIN) read_from_host();
    }
    feed_avr();
    flush_to_host();
    if ((fds[0].revents & (POLLIN | POLLHUP | POLLERR)) && read_control()) break;

    // 3. Paced: sleep until simulated time may run one step further, until the next byte
    // leaves the wire or the next host byte is due in, or until the host or the control
    // channel has something; run on at once if the simulation is a step or more behind.
    // While bytes move, a step is shorter than a byte time, so a reply the firmware starts
    // within a step still reaches the host when its first byte has left the wire.
    if (!opt.paced) continue;
    const uint64_t wall_cycles = cycles_at(monotonic_ns());
    const uint64_t sim = sim_cycles();
    const uint64_t lag = wall_cycles > sim ? wall_cycles - sim : 0;
    const int active = g_to_avr.len > 0 || g_tx.len > 0 ||
                       !uart_fifo_isempty(&g_uart->input) ||
                       sim - g_last_byte_cycle < active_cycles;
    const int64_t step_ns =
        active ? (int64_t)(g_uart->cycles_per_byte * 900000000ULL / freq) : PACED_IDLE_STEP_NS;
    int64_t sleep_ns = step_ns - (int64_t)(lag * 1000000000ULL / freq);
    uint64_t next_event = UINT64_MAX;  // sim_cycles() of the next byte due to move
    if (g_tx.len > 0) next_event = g_tx.due[g_tx.head] + g_cycle_offset;
    if (g_to_avr.len > 0 && g_arrivals.ready[g_arrivals.head] < next_event) {
      next_event = g_arrivals.ready[g_arrivals.head];
    }
    if (next_event != UINT64_MAX) {
      const int64_t until_event =
          next_event > wall_cycles ? (int64_t)((next_event - wall_cycles) * 1000000000ULL / freq)
                                   : 0;
      if (until_event < sleep_ns) sleep_ns = until_event;
    }
    if (sleep_ns < PACED_MIN_SLEEP_NS) continue;
    struct pollfd wait_fds[2] = {{STDIN_FILENO, POLLIN, 0}, {g_master, POLLIN, 0}};
    const struct timespec ts = {0, sleep_ns};
    ppoll(wait_fds, g_host_connected ? 2 : 1, &ts, NULL);  // EINTR: the loop checks g_stop
  }
done:
  fflush(g_ctl);
  return exit_code;
}
