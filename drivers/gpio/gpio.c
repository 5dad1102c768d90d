/*
 * Pulse trains and edge watching on GPIO lines (libgpiod v1).
 *
 * The pulse thread sleeps with clock_nanosleep(TIMER_ABSTIME) to the next
 * period boundary computed from the start time, not from "now": a late
 * wake-up shortens the next sleep instead of shifting every later pulse.
 * libgpiod v1 has no kernel debounce, so the edge thread debounces in
 * software: an edge is held back until debounce_us passes with no other
 * edge; a bounce inside that window cancels the pending edge.
 */
#include "gpio.h"
#include "clock.h"

#include <errno.h>
#include <gpiod.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define CONSUMER "vlff-camd"

static struct timespec to_ts(uint64_t ns) {
  return (struct timespec){(time_t)(ns / 1000000000u), (long)(ns % 1000000000u)};
}

static void sleep_until(uint64_t ns) {
  struct timespec ts = to_ts(ns);
  while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR) {}
}

/* Opens chip and finds line; on failure fills err naming the key. */
static struct gpiod_line *find_line(const char *chip, const char *line, struct gpiod_chip **out_chip, char *err,
                                    size_t errlen) {
  *out_chip = gpiod_chip_open_lookup(chip);
  if (!*out_chip) {
    snprintf(err, errlen, "key 'gpio.chip': cannot open GPIO chip '%s': %s", chip,
             errno ? strerror(errno) : "no such chip");
    return NULL;
  }
  char *end;
  long n = strtol(line, &end, 10);
  struct gpiod_line *l = NULL;
  if (*line && !*end) {
    if (n < 0 || (unsigned)n >= gpiod_chip_num_lines(*out_chip)) {
      snprintf(err, errlen, "key 'gpio.line': %s has %u lines, no line %ld", gpiod_chip_name(*out_chip),
               gpiod_chip_num_lines(*out_chip), n);
      goto fail;
    }
    l = gpiod_chip_get_line(*out_chip, (unsigned)n);
  } else {
    l = gpiod_chip_find_line(*out_chip, line);
  }
  if (!l) {
    snprintf(err, errlen, "key 'gpio.line': no line '%s' on %s", line, gpiod_chip_name(*out_chip));
    goto fail;
  }
  if (gpiod_line_is_used(l)) {
    const char *who = gpiod_line_consumer(l);
    snprintf(err, errlen, "key 'gpio.line': line %u of %s is busy (used by '%s')", gpiod_line_offset(l),
             gpiod_chip_name(*out_chip), who ? who : "the kernel");
    goto fail;
  }
  return l;
fail:
  gpiod_chip_close(*out_chip);
  *out_chip = NULL;
  return NULL;
}

static void request_failed(struct gpiod_line *l, struct gpiod_chip *c, char *err, size_t errlen) {
  int e = errno;
  if (e == EBUSY)
    snprintf(err, errlen, "key 'gpio.line': line %u of %s is busy", gpiod_line_offset(l), gpiod_chip_name(c));
  else
    snprintf(err, errlen, "key 'gpio.line': cannot request line %u of %s: %s", gpiod_line_offset(l),
             gpiod_chip_name(c), strerror(e));
}

/* ------------------------------------------------------------- output */

struct vlff_gpio_out {
  struct gpiod_chip *chip;
  struct gpiod_line *line;
  pthread_t thread;
  atomic_bool stop;
  uint64_t period_ns, width_ns;
  void (*on_pulse)(void *, uint64_t, uint64_t);
  void *ctx;
  _Atomic uint64_t pulses, late;
};

static void *out_main(void *arg) {
  struct vlff_gpio_out *g = arg;
  uint64_t start = vlff_now_ns() + g->period_ns, k = 0;
  while (!atomic_load(&g->stop)) {
    uint64_t due = start + k * g->period_ns;
    sleep_until(due);
    if (atomic_load(&g->stop)) break;
    gpiod_line_set_value(g->line, 1);
    uint64_t t = vlff_now_ns();
    uint64_t n = atomic_fetch_add(&g->pulses, 1) + 1;
    if (g->on_pulse) g->on_pulse(g->ctx, t, n);
    sleep_until(t + g->width_ns);
    gpiod_line_set_value(g->line, 0);
    k++;
    /* Asleep for more than a period (suspend, overload): skip the missed
     * slots rather than firing a burst of catch-up pulses. */
    uint64_t now = vlff_now_ns();
    if (now > start + k * g->period_ns + g->period_ns) {
      uint64_t missed = (now - (start + k * g->period_ns)) / g->period_ns;
      atomic_fetch_add(&g->late, missed);
      k += missed;
    }
  }
  return NULL;
}

struct vlff_gpio_out *vlff_gpio_out_start(const char *chip, const char *line, double rate_hz, double pulse_us,
                                          bool active_low, void (*on_pulse)(void *, uint64_t, uint64_t),
                                          void *ctx, char *err, size_t errlen) {
  if (!(rate_hz > 0) || !(pulse_us > 0) || pulse_us * 1e-6 >= 1.0 / rate_hz) {
    snprintf(err, errlen, "key 'gpio.pulse_us': pulse of %g us does not fit the period of %g Hz", pulse_us, rate_hz);
    return NULL;
  }
  struct vlff_gpio_out *g = calloc(1, sizeof *g);
  if (!g) return snprintf(err, errlen, "out of memory"), NULL;
  g->line = find_line(chip, line, &g->chip, err, errlen);
  if (!g->line) goto fail;
  /* libgpiod translates logical values through ACTIVE_LOW, so the thread
   * always writes 1 = active. */
  int flags = active_low ? GPIOD_LINE_REQUEST_FLAG_ACTIVE_LOW : 0;
  if (gpiod_line_request_output_flags(g->line, CONSUMER, flags, 0)) {
    request_failed(g->line, g->chip, err, errlen);
    goto fail;
  }
  g->period_ns = (uint64_t)(1e9 / rate_hz);
  g->width_ns = (uint64_t)(pulse_us * 1e3);
  g->on_pulse = on_pulse;
  g->ctx = ctx;
  atomic_init(&g->stop, false);
  atomic_init(&g->pulses, 0);
  atomic_init(&g->late, 0);
  if (pthread_create(&g->thread, NULL, out_main, g)) {
    snprintf(err, errlen, "cannot start the pulse thread");
    goto fail;
  }
  return g;
fail:
  if (g->chip) gpiod_chip_close(g->chip); /* releases a requested line too */
  free(g);
  return NULL;
}

void vlff_gpio_out_stop(struct vlff_gpio_out *g) {
  if (!g) return;
  atomic_store(&g->stop, true);
  pthread_join(g->thread, NULL);
  gpiod_line_set_value(g->line, 0);
  gpiod_chip_close(g->chip);
  free(g);
}

struct vlff_gpio_out_stats vlff_gpio_out_stats(const struct vlff_gpio_out *g) {
  return (struct vlff_gpio_out_stats){atomic_load(&g->pulses), atomic_load(&g->late)};
}

/* -------------------------------------------------------------- input */

struct vlff_gpio_in {
  struct gpiod_chip *chip;
  struct gpiod_line *line;
  pthread_t thread;
  atomic_bool stop;
  uint64_t debounce_ns;
  bool active_low;
  void (*on_edge)(void *, uint64_t, uint64_t);
  void *ctx;
  _Atomic uint64_t edges, bounced;
};

static void *in_main(void *arg) {
  struct vlff_gpio_in *g = arg;
  bool pending = false;
  uint64_t pending_t = 0;
  while (!atomic_load(&g->stop)) {
    uint64_t wait_ns = 100000000u; /* poll the stop flag every 100 ms */
    if (pending) {
      uint64_t now = vlff_now_ns(), due = pending_t + g->debounce_ns;
      wait_ns = due > now ? due - now : 0;
    }
    struct timespec ts = to_ts(wait_ns);
    int rc = gpiod_line_event_wait(g->line, &ts);
    if (rc < 0) {
      if (errno == EINTR) continue;
      break;
    }
    if (rc == 0) {
      if (pending && vlff_now_ns() >= pending_t + g->debounce_ns) {
        pending = false;
        uint64_t n = atomic_fetch_add(&g->edges, 1) + 1;
        if (g->on_edge) g->on_edge(g->ctx, pending_t, n);
      }
      continue;
    }
    struct gpiod_line_event ev;
    if (gpiod_line_event_read(g->line, &ev)) continue;
    uint64_t t = (uint64_t)ev.ts.tv_sec * 1000000000u + (uint64_t)ev.ts.tv_nsec;
    /* With ACTIVE_LOW libgpiod already reports the active edge as RISING. */
    bool active = ev.event_type == GPIOD_LINE_EVENT_RISING_EDGE;
    if (!g->debounce_ns) {
      if (active) {
        uint64_t n = atomic_fetch_add(&g->edges, 1) + 1;
        if (g->on_edge) g->on_edge(g->ctx, t, n);
      }
      continue;
    }
    if (pending) {
      /* Any edge inside the window means the line has not settled. */
      atomic_fetch_add(&g->bounced, 1);
      pending = false;
      if (!active) continue;
    }
    if (active) {
      pending = true;
      pending_t = t;
    }
  }
  return NULL;
}

struct vlff_gpio_in *vlff_gpio_in_start(const char *chip, const char *line, double debounce_us, bool active_low,
                                        void (*on_edge)(void *, uint64_t, uint64_t), void *ctx, char *err,
                                        size_t errlen) {
  struct vlff_gpio_in *g = calloc(1, sizeof *g);
  if (!g) return snprintf(err, errlen, "out of memory"), NULL;
  g->line = find_line(chip, line, &g->chip, err, errlen);
  if (!g->line) goto fail;
  int flags = active_low ? GPIOD_LINE_REQUEST_FLAG_ACTIVE_LOW : 0;
  if (gpiod_line_request_both_edges_events_flags(g->line, CONSUMER, flags)) {
    request_failed(g->line, g->chip, err, errlen);
    goto fail;
  }
  g->debounce_ns = (uint64_t)(debounce_us * 1e3);
  g->active_low = active_low;
  g->on_edge = on_edge;
  g->ctx = ctx;
  atomic_init(&g->stop, false);
  atomic_init(&g->edges, 0);
  atomic_init(&g->bounced, 0);
  if (pthread_create(&g->thread, NULL, in_main, g)) {
    snprintf(err, errlen, "cannot start the edge thread");
    goto fail;
  }
  return g;
fail:
  if (g->chip) gpiod_chip_close(g->chip);
  free(g);
  return NULL;
}

void vlff_gpio_in_stop(struct vlff_gpio_in *g) {
  if (!g) return;
  atomic_store(&g->stop, true);
  pthread_join(g->thread, NULL);
  gpiod_chip_close(g->chip);
  free(g);
}

struct vlff_gpio_in_stats vlff_gpio_in_stats(const struct vlff_gpio_in *g) {
  return (struct vlff_gpio_in_stats){atomic_load(&g->edges), atomic_load(&g->bounced)};
}
