/*
 * node.cpu_budget: the pool's size and the trainer's pacing (budget.h).
 */
#include "budget.h"

#include <errno.h>
#include <math.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include "clock.h"

int vlff_budget_threads(double budget, int threads) {
  if (threads <= 0) {
    long n = sysconf(_SC_NPROCESSORS_ONLN);
    threads = n > 0 ? (int)n : 1;
  }
  if (budget > 0 && threads > ceil(budget)) threads = (int)ceil(budget);
  return threads < 1 ? 1 : threads;
}

double vlff_process_cpu_s(void) {
  struct timespec ts;
  if (clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts)) return 0;
  return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

void vlff_pacer_init(struct vlff_pacer *p, double budget) {
  *p = (struct vlff_pacer){.budget = budget > 0 ? budget : 0, .used = -1};
  p->wall = p->win_wall[0] = p->last_step = vlff_seconds();
  p->cpu = p->win_cpu[0] = vlff_process_cpu_s();
  p->wins = 1;
}

/* Adds what was used since the last reading and pays budget x the time gone by. */
static void account(struct vlff_pacer *p) {
  double wall = vlff_seconds(), cpu = vlff_process_cpu_s();
  p->debt += (cpu - p->cpu) - p->budget * (wall - p->wall);
  p->debt = fmax(p->debt, -p->budget * PACER_CREDIT_S);
  p->debt = fmin(p->debt, p->budget * PACER_DEBT_S);
  p->wall = wall;
  p->cpu = cpu;
}

bool vlff_pacer_pace(struct vlff_pacer *p, bool want_step, double max_sleep_s, double *used) {
  account(p);
  *used = -1;
  if (p->wall - p->win_wall[p->wins - 1] >= PACER_WINDOW_S) {
    if (p->wins == PACER_WINDOWS + 1) {
      memmove(p->win_wall, p->win_wall + 1, PACER_WINDOWS * sizeof p->win_wall[0]);
      memmove(p->win_cpu, p->win_cpu + 1, PACER_WINDOWS * sizeof p->win_cpu[0]);
      p->wins--;
    }
    p->win_wall[p->wins] = p->wall;
    p->win_cpu[p->wins++] = p->cpu;
    p->used = (p->cpu - p->win_cpu[0]) / (p->wall - p->win_wall[0]);
    *used = p->used;
  }
  if (p->budget <= 0 || !want_step || p->debt <= 0 || p->wall - p->last_step >= PACER_DEBT_S) {
    if (want_step) p->last_step = p->wall;
    return true;
  }
  /* Sleeping costs this process nothing, so budget x the sleep repays the
   * debt unless other threads use CPU meanwhile; what they use is counted
   * at the next call. */
  double need = p->debt / p->budget, nap = fmin(need, max_sleep_s);
  struct timespec ts = {.tv_sec = (time_t)nap, .tv_nsec = (long)((nap - floor(nap)) * 1e9)};
  while (clock_nanosleep(CLOCK_MONOTONIC, 0, &ts, &ts) == EINTR) {
  }
  p->slept_s += nap;
  if (need > max_sleep_s) return false;
  p->last_step = vlff_seconds();
  return true;
}
