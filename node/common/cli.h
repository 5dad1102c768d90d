/*
 * vlff_cli: the command-line convention every vlff program follows.
 *
 * Contract
 *  - Options are parsed with getopt_long. Every program takes -h/--help
 *    (usage on stdout, exit 0) and -V/--version ("<prog> <version>" on
 *    stdout, exit 0); the version is the project's one version string.
 *  - A usage error (unknown option, missing value, wrong arguments) prints
 *    one line "<prog>: <what>" and then the usage on stderr and exits 2.
 *    Other errors print "<where>: <what>" on stderr (the config's format:
 *    <where> is the program, or file:line:col when a file is at fault) and
 *    exit 1.
 *  - vlff_cli_next() keeps getopt's global state (optind, optarg): one
 *    parse per process, on the main thread, except that a program with
 *    subcommands parses once more for the subcommand (vlff_cli_restart),
 *    which follows the same rules with its own usage. Nothing here
 *    allocates.
 */
#ifndef VLFF_CLI_H
#define VLFF_CLI_H

#include <getopt.h>
#include <signal.h>
#include <stdio.h>

#ifdef __cplusplus
extern "C" {
#endif

/* The end of every program's long option table: --help, --version, the
 * terminator. */
#define VLFF_CLI_COMMON_OPTIONS {"help", no_argument, NULL, 'h'}, {"version", no_argument, NULL, 'V'}, {NULL, 0, NULL, 0}

/* What vlff_cli_next() returns when the program should exit with *status. */
#define VLFF_CLI_EXIT (-2)

struct vlff_cli {
  const char *prog;  /* "vlff-node" */
  const char *usage; /* the full usage text, ending in a newline */
};

/* The project version ("0.1.0"), the same for every program and library. */
const char *vlff_version(void);

/* getopt_long over the program's own options. shortopts may start with '+'
 * (stop at the first non-option: programs with subcommands); 'h' and 'V'
 * are added. Returns the next option of the program's own, -1 when the
 * options end (argv[optind] is the first operand), or VLFF_CLI_EXIT after it
 * handled --help, --version (*status 0) or a usage error (*status 2, message
 * and usage on stderr). */
int vlff_cli_next(const struct vlff_cli *cli, int argc, char *const argv[], const char *shortopts,
                  const struct option *longopts, int *status);

/* Starts a new parse: the next vlff_cli_next() reads a subcommand's argv
 * (argv[0] the subcommand's name) from its start, with its own options. */
void vlff_cli_restart(void);

/* A usage error found by the program itself (bad operands, a value out of
 * range): "<prog>: <message>" and the usage on stderr. Returns 2. */
/* The signal (SIGINT, SIGTERM or SIGHUP) that asked the program to stop, 0 while
 * none has: set by the handlers vlff_cli_catch_stop installs. */
extern volatile sig_atomic_t vlff_cli_stop;
/* SIGINT, SIGTERM and SIGHUP (unless ignored, as nohup leaves it) set
 * vlff_cli_stop; without SA_RESTART, so a blocked
 * read or sleep returns EINTR and the loop around it sees the request.
 * SIGPIPE is ignored: a reader that went away is an EPIPE, not a death.
 * So is SIGXFSZ: a page file at the file-size limit (systemd's LimitFSIZE)
 * is a failed write, counted, not a killed node. */
void vlff_cli_catch_stop(void);

int vlff_cli_usage_error(const struct vlff_cli *cli, const char *fmt, ...) __attribute__((format(printf, 2, 3)));

/* Any other error: "<prog>: <message>" on stderr. Returns 1. */
int vlff_cli_error(const struct vlff_cli *cli, const char *fmt, ...) __attribute__((format(printf, 2, 3)));

/* A config file the program cannot run: the config parser's message, which
 * starts with "file:line:col:" (the file is where the fault is, so no program
 * name goes before it), on stderr. Returns 1, as every program exits then. */
int vlff_cli_config_error(const char *msg);

#ifdef __cplusplus
}
#endif

#endif
