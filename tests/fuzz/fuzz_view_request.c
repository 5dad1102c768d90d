/* libFuzzer target: what vlff-view parses of a client's WebSocket messages itself
 * (request.c; the frames are libwebsockets'). The first byte chooses: even, the
 * rest is a request's JSON text; odd, the rest is clientPublish message data (the
 * 5-byte header, then the JSON of a prompt set). Promises checked: no crash or read
 * past the bytes; a JSON value is returned only for input that is valid UTF-8 with
 * nothing but whitespace after the value, and it prints to JSON that parses again
 * to the same text; a refusal names its reason; the header is taken exactly when it
 * is 5 bytes or more starting with opcode 1, with the channel id little-endian. */
#include <json-c/json.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "view.h"

/* Whole UTF-8 sequences, no overlong forms, surrogates or values past U+10FFFF. */
static int utf8_ok(const unsigned char *s, size_t n) {
  for (size_t i = 0; i < n;) {
    unsigned c = s[i];
    size_t k = c < 0x80 ? 0 : (c & 0xe0) == 0xc0 ? 1 : (c & 0xf0) == 0xe0 ? 2 : (c & 0xf8) == 0xf0 ? 3 : 9;
    if (k == 9 || i + k >= n + (k ? 0 : 1)) return 0;
    uint32_t cp = k ? c & (0x3f >> k) : c;
    for (size_t j = 1; j <= k; j++) {
      if ((s[i + j] & 0xc0) != 0x80) return 0;
      cp = cp << 6 | (s[i + j] & 0x3f);
    }
    static const uint32_t min[] = {0, 0x80, 0x800, 0x10000};
    if (cp < min[k] || cp > 0x10ffff || (cp >= 0xd800 && cp <= 0xdfff)) return 0;
    i += k + 1;
  }
  return 1;
}

static void check_json(const char *s, size_t n) {
  char why[160];
  memset(why, 0x55, sizeof why);
  json_object *o = vlff_view_parse_json(s, n, why, sizeof why);
  if (!o) {
    if (!memchr(why, 0, sizeof why) || !why[0]) __builtin_trap();
    return;
  }
  if (!utf8_ok((const unsigned char *)s, n)) __builtin_trap();
  size_t len;
  const char *text = json_object_to_json_string_length(o, JSON_C_TO_STRING_PLAIN, &len);
  char *copy = malloc(len ? len : 1);
  if (copy) {
    memcpy(copy, text, len);
    json_object *again = vlff_view_parse_json(copy, len, why, sizeof why);
    size_t len2;
    if (!again || strcmp(json_object_to_json_string_length(again, JSON_C_TO_STRING_PLAIN, &len2), text))
      __builtin_trap();
    json_object_put(again);
    free(copy);
  }
  json_object_put(o);
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  if (size == 0) return 0;
  /* a copy of exactly the bytes, so that ASan sees any read past them */
  size_t n = size - 1;
  unsigned char *buf = malloc(n ? n : 1);
  if (!buf) return 0;
  memcpy(buf, data + 1, n);
  if (!(data[0] & 1)) {
    check_json((const char *)buf, n);
  } else {
    char why[160] = "";
    uint32_t ch = 0;
    int rc = vlff_view_publish_header(buf, n, &ch, why, sizeof why);
    if ((rc == 0) != (n >= 5 && buf[0] == 1)) __builtin_trap();
    if (rc == 0) {
      if (ch != ((uint32_t)buf[1] | (uint32_t)buf[2] << 8 | (uint32_t)buf[3] << 16 | (uint32_t)buf[4] << 24))
        __builtin_trap();
      check_json((const char *)buf + 5, n - 5);
    } else if (!why[0]) {
      __builtin_trap();
    }
  }
  free(buf);
  return 0;
}
