/*
 * A small DBC reader for the tests: messages (BO_), signals (SG_) and value
 * tables (VAL_), enough to decode frames the way cantools or SavvyCAN would,
 * from the text of configs/vlff.dbc alone. Little-endian (@1) and big-endian
 * (@0) unsigned/signed integer signals; no multiplexing.
 * Errors: -1 with a message "file:line: what" in err.
 */
#ifndef VLFF_TEST_DBC_H
#define VLFF_TEST_DBC_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#define DBC_NAME 64
#define DBC_MAX_SIGNALS 72
#define DBC_MAX_MESSAGES 32

struct dbc_signal {
  char name[DBC_NAME];
  int start, length;
  bool little_endian, is_signed;
  double scale, offset, min, max;
  char unit[16];
};

struct dbc_message {
  uint32_t id;
  char name[DBC_NAME];
  int dlc;
  int nsig;
  struct dbc_signal sig[DBC_MAX_SIGNALS];
};

struct dbc {
  int nmsg;
  struct dbc_message msg[DBC_MAX_MESSAGES];
};

int dbc_load(const char *path, struct dbc *db, char *err, size_t errlen);
const struct dbc_message *dbc_find_id(const struct dbc *db, uint32_t id);
const struct dbc_message *dbc_find_name(const struct dbc *db, const char *name);
const struct dbc_signal *dbc_signal(const struct dbc_message *m, const char *name);
/* Raw and physical value of a signal in data (len bytes). -1 if it does not fit. */
int dbc_raw(const struct dbc_signal *s, const uint8_t *data, int len, int64_t *raw);
int dbc_decode(const struct dbc_message *m, const char *signal, const uint8_t *data, int len, double *value);

#endif
