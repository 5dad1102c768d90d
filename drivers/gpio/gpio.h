/*
 * GPIO camera triggering through libgpiod 1.6 (the v1 character-device API).
 *
 * Contract
 *  - Chips are named as libgpiod's lookup accepts them: "gpiochip0",
 *    "/dev/gpiochip0", "0", or a label. Lines by number ("17") or by name.
 *  - *_start() return NULL with err filled when the chip is missing, the
 *    line does not exist, or the line is busy (the message names the
 *    current consumer); errors name the config key (gpio.chip / gpio.line).
 *  - Each object runs one thread; callbacks run on it and must be quick and
 *    must not call back into the object. *_stop() joins the thread, leaves
 *    an output line inactive, releases the line and frees the object
 *    (NULL accepted).
 *  - Timestamps are CLOCK_MONOTONIC ns: for pulses the time the line was
 *    driven active (read right after the ioctl returned), for edges the
 *    kernel's event timestamp.
 */
#ifndef VLFF_GPIO_H
#define VLFF_GPIO_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

struct vlff_gpio_out_stats {
  uint64_t pulses;
  uint64_t late;          /* pulses started more than a period late (skipped slots) */
};

/* Drives a pulse train: active for pulse_us every 1/rate_hz seconds,
 * scheduled on absolute deadlines so timing errors never accumulate.
 * on_pulse(ctx, t_ns, n) follows each rising (active) transition. */
struct vlff_gpio_out;
struct vlff_gpio_out *vlff_gpio_out_start(const char *chip, const char *line, double rate_hz, double pulse_us,
                                          bool active_low,
                                          void (*on_pulse)(void *ctx, uint64_t t_ns, uint64_t n), void *ctx,
                                          char *err, size_t errlen);
void vlff_gpio_out_stop(struct vlff_gpio_out *g);
struct vlff_gpio_out_stats vlff_gpio_out_stats(const struct vlff_gpio_out *g);

struct vlff_gpio_in_stats {
  uint64_t edges;         /* active edges delivered */
  uint64_t bounced;       /* edges discarded by the debounce */
};

/* Watches a line's edges. An active edge (rising, or falling when
 * active_low) is delivered once the line has stayed at its new level for
 * debounce_us (0 = every edge at once), with the edge's kernel timestamp. */
struct vlff_gpio_in;
struct vlff_gpio_in *vlff_gpio_in_start(const char *chip, const char *line, double debounce_us, bool active_low,
                                        void (*on_edge)(void *ctx, uint64_t t_ns, uint64_t n), void *ctx,
                                        char *err, size_t errlen);
void vlff_gpio_in_stop(struct vlff_gpio_in *g);
struct vlff_gpio_in_stats vlff_gpio_in_stats(const struct vlff_gpio_in *g);

#endif
