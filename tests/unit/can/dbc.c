/* DBC reader for the tests (see dbc.h). Line-oriented: the DBC grammar puts
 * each BO_ and SG_ on its own line, which is all this needs. */
#include "dbc.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int fail(char *err, size_t n, const char *path, int line, const char *what) {
  snprintf(err, n, "%s:%d: %s", path, line, what);
  return -1;
}

int dbc_load(const char *path, struct dbc *db, char *err, size_t errlen) {
  FILE *f = fopen(path, "r");
  if (!f) return fail(err, errlen, path, 0, "cannot open");
  memset(db, 0, sizeof *db);
  char buf[1024];
  int line = 0, rc = 0;
  struct dbc_message *cur = NULL;
  while (fgets(buf, sizeof buf, f)) {
    line++;
    char *p = buf;
    while (*p == ' ' || *p == '\t') p++;
    if (!strncmp(p, "BO_ ", 4)) {
      if (db->nmsg == DBC_MAX_MESSAGES) { rc = fail(err, errlen, path, line, "too many messages"); break; }
      cur = &db->msg[db->nmsg];
      unsigned long id;
      char name[DBC_NAME];
      int dlc;
      if (sscanf(p, "BO_ %lu %63[^:]: %d", &id, name, &dlc) != 3 || dlc < 0 || dlc > 64) {
        rc = fail(err, errlen, path, line, "bad BO_ line");
        break;
      }
      cur->id = (uint32_t)id;
      snprintf(cur->name, sizeof cur->name, "%s", name);
      cur->dlc = dlc;
      db->nmsg++;
    } else if (!strncmp(p, "SG_ ", 4)) {
      if (!cur) { rc = fail(err, errlen, path, line, "SG_ outside a message"); break; }
      if (cur->nsig == DBC_MAX_SIGNALS) { rc = fail(err, errlen, path, line, "too many signals"); break; }
      struct dbc_signal *s = &cur->sig[cur->nsig];
      char order, sign;
      int used = 0;
      if (sscanf(p, "SG_ %63s : %d|%d@%c%c (%lf,%lf) [%lf|%lf] \"%15[^\"]\"%n", s->name, &s->start, &s->length,
                 &order, &sign, &s->scale, &s->offset, &s->min, &s->max, s->unit, &used) < 10) {
        s->unit[0] = 0;
        if (sscanf(p, "SG_ %63s : %d|%d@%c%c (%lf,%lf) [%lf|%lf] \"\"%n", s->name, &s->start, &s->length, &order,
                   &sign, &s->scale, &s->offset, &s->min, &s->max, &used) < 9) {
          rc = fail(err, errlen, path, line, "bad SG_ line");
          break;
        }
      }
      if ((order != '0' && order != '1') || (sign != '+' && sign != '-') || s->length < 1 || s->length > 64 ||
          s->start < 0 || s->scale == 0) {
        rc = fail(err, errlen, path, line, "bad SG_ field");
        break;
      }
      s->little_endian = order == '1';
      s->is_signed = sign == '-';
      cur->nsig++;
    } else if (*p != '\n' && *p != '\r' && *p != 0) {
      cur = NULL; /* CM_, BA_, VAL_, ... end the message block */
    }
  }
  fclose(f);
  return rc;
}

const struct dbc_message *dbc_find_id(const struct dbc *db, uint32_t id) {
  for (int i = 0; i < db->nmsg; i++)
    if (db->msg[i].id == id) return &db->msg[i];
  return NULL;
}

const struct dbc_message *dbc_find_name(const struct dbc *db, const char *name) {
  for (int i = 0; i < db->nmsg; i++)
    if (!strcmp(db->msg[i].name, name)) return &db->msg[i];
  return NULL;
}

const struct dbc_signal *dbc_signal(const struct dbc_message *m, const char *name) {
  for (int i = 0; i < m->nsig; i++)
    if (!strcmp(m->sig[i].name, name)) return &m->sig[i];
  return NULL;
}

int dbc_raw(const struct dbc_signal *s, const uint8_t *data, int len, int64_t *raw) {
  uint64_t v = 0;
  if (s->little_endian) {
    if (s->start + s->length > len * 8) return -1;
    for (int i = 0; i < s->length; i++) {
      int bit = s->start + i;
      v |= (uint64_t)((data[bit / 8] >> (bit % 8)) & 1) << i;
    }
  } else {
    /* Motorola: start is the MSB, bits run down within a byte, then to the next byte. */
    int bit = s->start;
    for (int i = 0; i < s->length; i++) {
      if (bit / 8 >= len) return -1;
      v = (v << 1) | ((data[bit / 8] >> (bit % 8)) & 1);
      bit = (bit % 8 == 0) ? bit + 15 : bit - 1;
    }
  }
  if (s->is_signed && s->length < 64 && (v >> (s->length - 1)) & 1) v |= ~0ULL << s->length;
  *raw = (int64_t)v;
  return 0;
}

int dbc_decode(const struct dbc_message *m, const char *signal, const uint8_t *data, int len, double *value) {
  const struct dbc_signal *s = dbc_signal(m, signal);
  int64_t raw;
  if (!s || dbc_raw(s, data, len, &raw) < 0) return -1;
  *value = s->is_signed ? (double)raw * s->scale + s->offset : (double)(uint64_t)raw * s->scale + s->offset;
  return 0;
}
