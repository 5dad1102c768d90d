/*
 * vlff escaping: outside data quoted in a message, made safe for a terminal.
 *
 * Every message of the project that quotes bytes it did not write itself (a
 * line of a file, a file name from a directory listing, a path given on the
 * command line, a segment name, text from a ring, the mailbox or a network
 * peer) passes them through this one routine, so that an escape sequence
 * (OSC, CSI), a carriage return or newline, a NUL or binary garbage in them
 * cannot retitle, clear or rewrite the terminal, forge another log line, or
 * cut the message short.
 *
 * Header only (static inline) so that libvlff-shm, which links nothing of
 * node/common, and node/common, which links libvlff-shm, share one copy of
 * the rules. In-tree only: it is not installed, and vlff/shm.h must not
 * include it.
 *
 * Contract (vlff_escape)
 *  - Printable ASCII (0x20..0x7e) is copied, except: a backslash becomes
 *    "\\", a single quote "\'", a double quote "\"", so a quote cannot end
 *    the quoting a message puts around the text.
 *  - Every other byte that is written escaped is written as "\xNN" (two
 *    lower-case hex digits): control bytes (C0 with NUL, tab, CR, LF and ESC,
 *    and DEL), bytes that are not part of valid UTF-8 (stray continuation
 *    bytes, overlong forms, surrogates, code points above U+10FFFF, a
 *    sequence cut short), and the bytes of the valid UTF-8 characters that
 *    still act on a terminal or on how the line reads: the C1 controls
 *    U+0080..U+009F (U+009B is CSI on some terminals), the line and
 *    paragraph separators U+2028/U+2029 and the bidirectional embeddings,
 *    overrides and isolates U+202A..U+202E, U+2066..U+2069.
 *  - Every other valid UTF-8 sequence (2 to 4 bytes) is copied as is: names
 *    in other scripts are legitimate.
 *  - Bounded: at most max input bytes are read, and the output never
 *    exceeds outlen bytes with its NUL. An escape or a UTF-8 character is
 *    never cut in half. When not every one of the n input bytes made it
 *    into the output, "..." ends it.
 *  - outlen must be at least 8; out is always NUL-terminated and returned,
 *    so a call can be a printf argument.
 *  - Pure: no allocation, no global state, thread- and signal-safe.
 */
#ifndef VLFF_ESCAPE_H
#define VLFF_ESCAPE_H

#include <stddef.h>
#include <string.h>

/* Output buffer of VLFF_Q and friends: room for 127 escaped bytes at worst,
 * 507 printable ones. */
#define VLFF_ESC_LEN 512

/* Length of the valid UTF-8 sequence at s (at most n bytes), with its code
 * point in *cp; 0 if none starts there. */
static inline size_t vlff_utf8_len(const unsigned char *s, size_t n, unsigned long *cp) {
  unsigned char c = s[0];
  size_t len;
  unsigned long v, min;
  if (c >= 0xc2 && c <= 0xdf) len = 2, v = c & 0x1fu, min = 0x80;
  else if (c >= 0xe0 && c <= 0xef) len = 3, v = c & 0x0fu, min = 0x800;
  else if (c >= 0xf0 && c <= 0xf4) len = 4, v = c & 0x07u, min = 0x10000;
  else return 0;
  if (len > n) return 0;
  for (size_t k = 1; k < len; k++) {
    if ((s[k] & 0xc0) != 0x80) return 0;
    v = (v << 6) | (s[k] & 0x3fu);
  }
  if (v < min || v > 0x10ffff || (v >= 0xd800 && v <= 0xdfff)) return 0;
  *cp = v;
  return len;
}

/* Whether a valid code point still acts on a terminal or on how the line
 * reads (see the contract). */
static inline int vlff_escape_cp(unsigned long cp) {
  return (cp >= 0x80 && cp <= 0x9f) || cp == 0x2028 || cp == 0x2029 || (cp >= 0x202a && cp <= 0x202e) ||
         (cp >= 0x2066 && cp <= 0x2069);
}

static inline char *vlff_escape(char *out, size_t outlen, const void *data, size_t n, size_t max) {
  static const char hex[] = "0123456789abcdef";
  const unsigned char *s = (const unsigned char *)data;
  size_t o = 0, i = 0, lim = n < max ? n : max;
  if (!s) lim = n = 0;
  while (i < lim) {
    unsigned char c = s[i];
    char unit[16];
    size_t w = 0, used = 1;
    unsigned long cp = 0;
    if (c >= 0x20 && c < 0x7f) {
      if (c == '\\' || c == '\'' || c == '"') unit[w++] = '\\';
      unit[w++] = (char)c;
    } else {
      size_t l = c >= 0x80 ? vlff_utf8_len(s + i, lim - i, &cp) : 0;
      if (l && !vlff_escape_cp(cp)) {
        memcpy(unit, s + i, l);
        w = used = l;
      } else {
        used = l ? l : 1;
        for (size_t k = 0; k < used; k++) {
          unit[w++] = '\\';
          unit[w++] = 'x';
          unit[w++] = hex[s[i + k] >> 4];
          unit[w++] = hex[s[i + k] & 15];
        }
      }
    }
    /* room for this unit, a "..." that may follow and the NUL */
    if (o + w + 4 > outlen) break;
    memcpy(out + o, unit, w);
    o += w;
    i += used;
  }
  if (i < n && o + 4 <= outlen) {
    memcpy(out + o, "...", 3);
    o += 3;
  }
  if (outlen) out[o < outlen ? o : outlen - 1] = 0;
  return out;
}

/* A NUL-terminated string, escaped whole up to the bound of out; NULL is
 * written "(null)". */
static inline char *vlff_escape_str(char *out, size_t outlen, const char *s) {
  if (!s) s = "(null)";
  return vlff_escape(out, outlen, s, strlen(s), (size_t)-1);
}

#ifndef __cplusplus
/* The escaped text as a printf argument, in a buffer that lives until the
 * end of the enclosing block (a compound literal), e.g.
 *   vlff_errf(err, len, "%s: got '%s'", VLFF_Q(path), VLFF_QMAX(line, 40));
 * VLFF_Q: a NUL-terminated string (NULL allowed); VLFF_QN: n bytes that may
 * hold NULs; VLFF_QMAX: a string of which at most max bytes are quoted. */
#define VLFF_Q(s) vlff_escape_str((char[VLFF_ESC_LEN]){0}, VLFF_ESC_LEN, (s))
#define VLFF_QN(s, n) vlff_escape((char[VLFF_ESC_LEN]){0}, VLFF_ESC_LEN, (s), (n), (size_t)-1)
#define VLFF_QMAX(s, max) vlff_escape((char[VLFF_ESC_LEN]){0}, VLFF_ESC_LEN, (s), strlen(s), (max))
#endif

#endif
