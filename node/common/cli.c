/*
 * The shared half of every vlff program's command line: getopt_long with the
 * help/version/usage-error behaviour fixed in one place, so that the programs
 * cannot drift apart again (they once answered --version in four ways).
 */
#include "cli.h"

#include <stdarg.h>
#include <string.h>

#ifndef VLFF_VERSION
#error "VLFF_VERSION must come from the project version (CMake)"
#endif

const char *vlff_version(void) { return VLFF_VERSION; }

static void vmessage(const struct vlff_cli *cli, const char *fmt, va_list ap) {
  fprintf(stderr, "%s: ", cli->prog);
  vfprintf(stderr, fmt, ap);
  fputc('\n', stderr);
}

int vlff_cli_usage_error(const struct vlff_cli *cli, const char *fmt, ...) {
  va_list ap;
  va_start(ap, fmt);
  vmessage(cli, fmt, ap);
  va_end(ap);
  fputs(cli->usage, stderr);
  return 2;
}

int vlff_cli_error(const struct vlff_cli *cli, const char *fmt, ...) {
  va_list ap;
  va_start(ap, fmt);
  vmessage(cli, fmt, ap);
  va_end(ap);
  return 1;
}

int vlff_cli_config_error(const char *msg) {
  fprintf(stderr, "%s\n", msg);
  return 1;
}

/* glibc: optind 0 reinitialises getopt, its permutation state included
 * (optind 1 would keep state from the previous argv). */
void vlff_cli_restart(void) { optind = 0; }

int vlff_cli_next(const struct vlff_cli *cli, int argc, char *const argv[], const char *shortopts,
                  const struct option *longopts, int *status) {
  /* ':' first makes getopt report a missing value as ':' and print nothing
   * itself; its own messages would be a second, differently worded line. */
  char spec[128];
  const char *own = shortopts ? shortopts : "";
  const char *order = "";
  if (*own == '+' || *own == '-') {
    order = *own == '+' ? "+" : "-";
    own++;
  }
  snprintf(spec, sizeof spec, "%s:%shV", order, own);
  opterr = 0;
  int c = getopt_long(argc, argv, spec, longopts, NULL);
  const char *arg = optind > 0 && optind <= argc ? argv[optind - 1] : "?";
  switch (c) {
  case 'h':
    fputs(cli->usage, stdout);
    *status = 0;
    return VLFF_CLI_EXIT;
  case 'V':
    printf("%s %s\n", cli->prog, VLFF_VERSION);
    *status = 0;
    return VLFF_CLI_EXIT;
  case ':':
    if (optopt && strncmp(arg, "--", 2) != 0)
      *status = vlff_cli_usage_error(cli, "option '-%c' needs a value", optopt);
    else
      *status = vlff_cli_usage_error(cli, "option '%s' needs a value", arg);
    return VLFF_CLI_EXIT;
  case '?':
    if (strncmp(arg, "--", 2) == 0 && optopt)
      *status = vlff_cli_usage_error(cli, "option '%s' takes no value", arg);
    else if (optopt)
      *status = vlff_cli_usage_error(cli, "unknown option '-%c'", optopt);
    else
      *status = vlff_cli_usage_error(cli, "unknown option '%s'", arg);
    return VLFF_CLI_EXIT;
  default: return c;
  }
}

volatile sig_atomic_t vlff_cli_stop;

static void on_stop(int sig) { vlff_cli_stop = sig; }

void vlff_cli_catch_stop(void) {
  struct sigaction sa;
  memset(&sa, 0, sizeof sa);
  sa.sa_handler = on_stop;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGINT, &sa, NULL);
  sigaction(SIGTERM, &sa, NULL);
  /* a hang-up (the terminal or ssh session gone) stops as cleanly: its
   * default action killed the node with no log line and no checkpoint.
   * One ignored on purpose (nohup) stays ignored. */
  struct sigaction hup;
  if (sigaction(SIGHUP, NULL, &hup) == 0 && hup.sa_handler != SIG_IGN) sigaction(SIGHUP, &sa, NULL);
  signal(SIGPIPE, SIG_IGN);
  signal(SIGXFSZ, SIG_IGN);
}
