/*
 * Depth registration of a 640x480 depth image into a 640x480 colour camera
 * (depthreg.c), against two baselines measured on the same data in the
 * same run: a plain copy of the depth image (the floor of any per-frame
 * pass over it) and the per-pixel unit conversion the pipeline does for an
 * unregistered range image. The scene is a slanted plane with a box in
 * front, seen through a distorted lens, 5 cm from the colour camera: edges,
 * occlusion and holes as a real rig has them. Medians of many runs of
 * thread CPU time, interleaved so that machine noise falls on all three
 * alike.
 */
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "bench_stats.h"
#include "depthreg.h"

#define W 640
#define H 480
#define RUNS 200

/* This thread's CPU time: on a shared host the wall clock also counts the
 * time other processes hold the core. */
static double now_ms(void) {
  struct timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return ts.tv_sec * 1e3 + ts.tv_nsec * 1e-6;
}

static void cpu_model(char *out, size_t len) {
  snprintf(out, len, "unknown");
  FILE *f = fopen("/proc/cpuinfo", "r");
  if (!f) return;
  char line[256];
  while (fgets(line, sizeof line, f))
    if (!strncmp(line, "model name", 10) && strchr(line, ':')) {
      snprintf(out, len, "%s", strchr(line, ':') + 2);
      out[strcspn(out, "\n")] = 0;
      break;
    }
  fclose(f);
}

int main(void) {
  struct vlff_rgbd_calib c;
  memset(&c, 0, sizeof c);
  const double kd[9] = {520, 0, 319.4, 0, 521, 239.6, 0, 0, 1}, kc[9] = {525, 0, 319.2, 0, 523, 241.1, 0, 0, 1};
  const double dd[5] = {-0.12, 0.06, 0.0008, -0.0005, -0.01};
  memcpy(c.kd, kd, sizeof kd), memcpy(c.kc, kc, sizeof kc), memcpy(c.dd, dd, sizeof dd);
  c.nd = c.nc = 5;
  const double a = 2 * M_PI / 180; /* two degrees of yaw between the cameras */
  const double r[9] = {cos(a), 0, sin(a), 0, 1, 0, -sin(a), 0, cos(a)};
  memcpy(c.r, r, sizeof r);
  c.t[0] = -0.052, c.t[1] = 0.004, c.t[2] = 0.008;
  char err[512];
  struct vlff_depthreg *reg = vlff_depthreg_new(&c, W, H, W, H, 0, 0, err, sizeof err);
  if (!reg) return fprintf(stderr, "bench_register: %s\n", err), 1;
  uint16_t *depth = malloc(W * H * 2), *out = malloc(W * H * 2);
  float *metres = malloc(W * H * sizeof(float));
  if (!depth || !out || !metres) return fprintf(stderr, "bench_register: out of memory\n"), 1;
  /* Millimetres: a plane rising from 1.8 m to 2.6 m left to right, a box at
   * 1.2 m in the middle, a few percent of dropouts as a ToF camera has. */
  srand(1);
  for (int y = 0; y < H; y++)
    for (int x = 0; x < W; x++) {
      int box = x > 220 && x < 420 && y > 160 && y < 340;
      depth[y * W + x] = rand() % 50 == 0 ? 0 : (uint16_t)(box ? 1200 + (x - 220) : 1800 + 800 * x / W);
    }
  double t_reg[RUNS], t_copy[RUNS], t_conv[RUNS];
  long valid = 0;
  volatile uint32_t sink = 0;
  for (int i = 0; i < RUNS; i++) {
    double t0 = now_ms();
    valid = vlff_depthreg_apply(reg, depth, W * 2, 0.001, out, W * 2, err, sizeof err);
    double t1 = now_ms();
    for (int y = 0; y < H; y++) memcpy(out + y * W, depth + y * W, W * 2);
    double t2 = now_ms();
    for (int k = 0; k < W * H; k++) metres[k] = depth[k] * 0.001f;
    double t3 = now_ms();
    sink += out[i % (W * H)] + (uint32_t)metres[i % (W * H)];
    (void)sink;
    t_reg[i] = t1 - t0, t_copy[i] = t2 - t1, t_conv[i] = t3 - t2;
  }
  if (valid < 0) return fprintf(stderr, "bench_register: %s\n", err), 1;
  double reg_ms = bench_median(t_reg, RUNS), copy_ms = bench_median(t_copy, RUNS),
         conv_ms = bench_median(t_conv, RUNS);
  char cpu[128];
  cpu_model(cpu, sizeof cpu);
  printf("cpu: %s\n", cpu);
  printf("register 640x480 -> 640x480: %.3f ms CPU, median of %d (%ld of %d pixels valid)\n", reg_ms, RUNS, valid, W * H);
  printf("baselines: copy %.3f ms, mm -> metres %.3f ms\n", copy_ms, conv_ms);
  printf("RESULT register_ms_vga=%.3f copy_ms_vga=%.3f register_vs_copy=%.1f register_vs_convert=%.1f\n", reg_ms,
         copy_ms, reg_ms / copy_ms, reg_ms / conv_ms);
  vlff_depthreg_free(reg);
  free(depth), free(out), free(metres);
  return 0;
}
