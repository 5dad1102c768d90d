/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * request.c - what the viewer itself parses of a client's WebSocket messages (the
 * frames are libwebsockets'): the JSON text of a request or of a published
 * message, and the binary header of clientPublish message data.
 *
 * json-c's tokener alone returns the first JSON value and ignores what follows it,
 * and takes bytes that are not UTF-8 into strings (its own check lets encoded
 * surrogates through): a request is checked here to be UTF-8 (RFC 3629: no overlong
 * form, surrogate or value past U+10FFFF), parsed in strict mode, and anything after
 * the value but whitespace refuses it.
 */
#include <json-c/json.h>
#include <stdio.h>
#include <string.h>

#include "view.h"

/* The offset of the first byte that does not start a valid UTF-8 sequence, or n. */
static size_t utf8_valid_prefix(const unsigned char *s, size_t n) {
  static const uint32_t min[] = {0, 0x80, 0x800, 0x10000};
  for (size_t i = 0; i < n;) {
    unsigned c = s[i];
    size_t k = c < 0x80 ? 0 : (c & 0xe0) == 0xc0 ? 1 : (c & 0xf0) == 0xe0 ? 2 : (c & 0xf8) == 0xf0 ? 3 : 4;
    if (k == 4 || k >= n - i) return i;
    uint32_t cp = k ? c & (0x3fu >> k) : c;
    for (size_t j = 1; j <= k; j++) {
      if ((s[i + j] & 0xc0) != 0x80) return i;
      cp = cp << 6 | (s[i + j] & 0x3fu);
    }
    if (cp < min[k] || cp > 0x10ffff || (cp >= 0xd800 && cp <= 0xdfff)) return i;
    i += k + 1;
  }
  return n;
}

struct json_object *vlff_view_parse_json(const char *s, size_t n, char *why, size_t len) {
  if (n > (size_t)INT32_MAX) {
    snprintf(why, len, "%zu bytes of JSON are too many", n);
    return NULL;
  }
  size_t bad = utf8_valid_prefix((const unsigned char *)s, n);
  if (bad < n) {
    snprintf(why, len, "the text is not UTF-8 at byte %zu", bad);
    return NULL;
  }
  struct json_tokener *tok = json_tokener_new();
  if (!tok) {
    snprintf(why, len, "out of memory");
    return NULL;
  }
  /* trailing bytes are let through here only to be named below */
  json_tokener_set_flags(tok, JSON_TOKENER_STRICT | JSON_TOKENER_ALLOW_TRAILING_CHARS | JSON_TOKENER_VALIDATE_UTF8);
  json_object *o = json_tokener_parse_ex(tok, s, (int)n);
  enum json_tokener_error err = json_tokener_get_error(tok);
  size_t end = json_tokener_get_parse_end(tok);
  if (!o && err == json_tokener_continue) {
    /* the text ended: a NUL tells the tokener so (a number at the very end is
     * otherwise waiting for more digits) */
    o = json_tokener_parse_ex(tok, "", 1);
    err = json_tokener_get_error(tok);
    end = n;
  }
  if (!o || err != json_tokener_success) {
    /* a complete value whose text ends early is "continue": name it as unfinished */
    snprintf(why, len, "%s at byte %zu",
             err == json_tokener_continue ? "unexpected end of the text" : json_tokener_error_desc(err), end);
    json_object_put(o);
    json_tokener_free(tok);
    return NULL;
  }
  json_tokener_free(tok);
  while (end < n && strchr(" \t\r\n", s[end]) && s[end]) end++;
  if (end < n) {
    snprintf(why, len, "bytes after the JSON value (at byte %zu of %zu)", end, n);
    json_object_put(o);
    return NULL;
  }
  return o;
}

int vlff_view_publish_header(const unsigned char *d, size_t n, uint32_t *channel, char *why, size_t len) {
  if (n < 5) {
    snprintf(why, len, "binary message of %zu bytes is shorter than its 5-byte header", n);
    return -1;
  }
  if (d[0] != 1) {
    snprintf(why, len, "binary opcode %u is not supported (1 = message data)", d[0]);
    return -1;
  }
  *channel = (uint32_t)d[1] | (uint32_t)d[2] << 8 | (uint32_t)d[3] << 16 | (uint32_t)d[4] << 24;
  return 0;
}
