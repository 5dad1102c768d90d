/*
 * CLIP's BPE tokenizer. The reference (openai/CLIP simple_tokenizer.py)
 * works on Python strings; we work on code points and symbol ids instead:
 * every vocabulary string gets its id once at load time, merges become an
 * (id, id) -> (rank, id) hash table, and a word is an id array that merges
 * shrink in place. Ids are resolved "last wins" exactly like the
 * reference's dict(zip(vocab, range(len(vocab)))), so even a merges file
 * with repeated strings tokenizes identically.
 */
#include "tokenizer.h"
#include "hash.h"

#include <errno.h>
#include <stdarg.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
#include <zlib.h>

#include "unicode_tables.h"
#include "files.h"
#include "log.h"

#define NUM_MERGES (49152 - 256 - 2)  /* the reference's merges[1:49152-256-2+1] */
#define MAX_FILE_BYTES (64u << 20)    /* a gzip bomb stops here */
#define STR_SLOTS (1u << 17)
#define PAIR_SLOTS (1u << 17)

struct pair_slot {
  uint64_t key;  /* (a << 32 | b) + 1; 0 = empty */
  int32_t rank;
  int32_t id;
};

struct vlff_tokenizer {
  char *strings[VLFF_CLIP_VOCAB];  /* vocabulary, index = token id */
  int32_t str_slot[STR_SLOTS];     /* string hash: token id + 1, 0 = empty */
  struct pair_slot pairs[PAIR_SLOTS];
  int32_t byte_id[256];            /* byte -> id of its symbol */
  int32_t byte_eow[256];           /* byte -> id of its symbol + "</w>" */
};



static int32_t str_lookup(const struct vlff_tokenizer *t, const char *s, size_t n) {
  for (uint64_t h = vlff_fnv1a64(VLFF_FNV1A64_INIT, s, n);; h++) {
    int32_t v = t->str_slot[h & (STR_SLOTS - 1)];
    if (!v) return -1;
    const char *c = t->strings[v - 1];
    if (strlen(c) == n && !memcmp(c, s, n)) return v - 1;
  }
}

/* Later ids replace earlier ones for the same string, as the reference's dict. */
static void str_insert(struct vlff_tokenizer *t, int32_t id) {
  const char *s = t->strings[id];
  size_t n = strlen(s);
  for (uint64_t h = vlff_fnv1a64(VLFF_FNV1A64_INIT, s, n);; h++) {
    int32_t *slot = &t->str_slot[h & (STR_SLOTS - 1)];
    if (!*slot || !strcmp(t->strings[*slot - 1], s)) {
      *slot = id + 1;
      return;
    }
  }
}

static uint64_t pair_hash(uint64_t key) {
  key ^= key >> 33;
  key *= 0xff51afd7ed558ccdull;
  key ^= key >> 33;
  return key;
}

static const struct pair_slot *pair_lookup(const struct vlff_tokenizer *t, int32_t a, int32_t b) {
  uint64_t key = ((uint64_t)(uint32_t)a << 32 | (uint32_t)b) + 1;
  for (uint64_t h = pair_hash(key);; h++) {
    const struct pair_slot *p = &t->pairs[h & (PAIR_SLOTS - 1)];
    if (!p->key) return NULL;
    if (p->key == key) return p;
  }
}

static void pair_insert(struct vlff_tokenizer *t, int32_t a, int32_t b, int32_t rank, int32_t id) {
  uint64_t key = ((uint64_t)(uint32_t)a << 32 | (uint32_t)b) + 1;
  for (uint64_t h = pair_hash(key);; h++) {
    struct pair_slot *p = &t->pairs[h & (PAIR_SLOTS - 1)];
    if (!p->key || p->key == key) {
      p->key = key;
      p->rank = rank;
      p->id = id;
      return;
    }
  }
}

/* ---- UTF-8 -------------------------------------------------------------- */

static size_t utf8_put(uint32_t cp, char *out) {
  if (cp < 0x80) {
    out[0] = (char)cp;
    return 1;
  }
  if (cp < 0x800) {
    out[0] = (char)(0xC0 | cp >> 6);
    out[1] = (char)(0x80 | (cp & 0x3F));
    return 2;
  }
  if (cp < 0x10000) {
    out[0] = (char)(0xE0 | cp >> 12);
    out[1] = (char)(0x80 | (cp >> 6 & 0x3F));
    out[2] = (char)(0x80 | (cp & 0x3F));
    return 3;
  }
  out[0] = (char)(0xF0 | cp >> 18);
  out[1] = (char)(0x80 | (cp >> 12 & 0x3F));
  out[2] = (char)(0x80 | (cp >> 6 & 0x3F));
  out[3] = (char)(0x80 | (cp & 0x3F));
  return 4;
}

/* Strict decoding (no overlongs, surrogates or code points past U+10FFFF):
 * the reference only ever sees valid Python strings. Returns the number of
 * code points, or -1 with *bad = offset of the first invalid byte. */
static long utf8_decode(const char *s, size_t n, uint32_t *out, size_t *bad) {
  size_t i = 0, k = 0;
  while (i < n) {
    uint8_t c = (uint8_t)s[i];
    uint32_t cp;
    size_t len;
    if (c < 0x80) {
      cp = c, len = 1;
    } else if (c >= 0xC2 && c <= 0xDF) {
      cp = c & 0x1F, len = 2;
    } else if (c >= 0xE0 && c <= 0xEF) {
      cp = c & 0x0F, len = 3;
    } else if (c >= 0xF0 && c <= 0xF4) {
      cp = c & 0x07, len = 4;
    } else {
      *bad = i;
      return -1;
    }
    if (i + len > n) {
      *bad = i;
      return -1;
    }
    for (size_t j = 1; j < len; j++) {
      uint8_t cc = (uint8_t)s[i + j];
      if ((cc & 0xC0) != 0x80) {
        *bad = i;
        return -1;
      }
      cp = cp << 6 | (cc & 0x3F);
    }
    if ((len == 3 && (cp < 0x800 || (cp >= 0xD800 && cp <= 0xDFFF))) || (len == 4 && (cp < 0x10000 || cp > 0x10FFFF))) {
      *bad = i;
      return -1;
    }
    out[k++] = cp;
    i += len;
  }
  return (long)k;
}

/* ---- Unicode classes ----------------------------------------------------- */

static bool in_ranges(const struct vlff_uni_range *r, size_t n, uint32_t cp) {
  size_t lo = 0, hi = n;
  while (lo < hi) {
    size_t mid = (lo + hi) / 2;
    if (cp < r[mid].lo) hi = mid;
    else if (cp > r[mid].hi) lo = mid + 1;
    else return true;
  }
  return false;
}

static bool is_letter(uint32_t cp) {
  if (cp < 0x80) return (cp | 0x20) >= 'a' && (cp | 0x20) <= 'z';
  return in_ranges(vlff_uni_letters, vlff_uni_letters_count, cp);
}

static bool is_number(uint32_t cp) {
  if (cp < 0x80) return cp >= '0' && cp <= '9';
  return in_ranges(vlff_uni_numbers, vlff_uni_numbers_count, cp);
}

/* Python's str.isspace(), which both re's \s and str.strip() use. */
static bool is_space(uint32_t cp) {
  return (cp >= 0x09 && cp <= 0x0D) || (cp >= 0x1C && cp <= 0x20) || cp == 0x85 || cp == 0xA0 || cp == 0x1680 ||
         (cp >= 0x2000 && cp <= 0x200A) || cp == 0x2028 || cp == 0x2029 || cp == 0x202F || cp == 0x205F ||
         cp == 0x3000;
}

static uint32_t to_lower(uint32_t cp) {
  if (cp < 0x80) return (cp >= 'A' && cp <= 'Z') ? cp + 32 : cp;
  size_t lo = 0, hi = vlff_uni_lower_count;
  while (lo < hi) {
    size_t mid = (lo + hi) / 2;
    if (cp < vlff_uni_lower[mid].from) hi = mid;
    else if (cp > vlff_uni_lower[mid].from) lo = mid + 1;
    else return vlff_uni_lower[mid].to;
  }
  return cp;
}

/* ---- Cleaning: ftfy.fix_text's steps that plain prompts meet, html.unescape --- */

/* Windows-1252 for 0x80..0x9F: both ftfy's C1 fix and html.unescape's
 * numeric references map these; 0 = left as is. */
static const uint16_t cp1252[32] = {
    0x20AC, 0,      0x201A, 0x0192, 0x201E, 0x2026, 0x2020, 0x2021, 0x02C6, 0x2030, 0x0160,
    0x2039, 0x0152, 0,      0x017D, 0,      0,      0x2018, 0x2019, 0x201C, 0x201D, 0x2022,
    0x2013, 0x2014, 0x02DC, 0x2122, 0x0161, 0x203A, 0x0153, 0,      0x017E, 0x0178};

struct entity {
  const char *name;
  uint32_t cp;
  bool legacy; /* HTML4 name that html.unescape also accepts without ';' */
};

/* Entities a prompt plausibly holds; html.unescape knows ~2200, the rest of
 * which are left as literal text here (documented in docs/vlm.md). */
static const struct entity entities[] = {
    {"amp", '&', true},      {"lt", '<', true},        {"gt", '>', true},         {"quot", '"', true},
    {"apos", '\'', false},   {"nbsp", 0xA0, true},     {"copy", 0xA9, true},      {"reg", 0xAE, true},
    {"deg", 0xB0, true},     {"times", 0xD7, true},    {"divide", 0xF7, true},    {"laquo", 0xAB, true},
    {"raquo", 0xBB, true},   {"middot", 0xB7, true},   {"para", 0xB6, true},      {"sect", 0xA7, true},
    {"cent", 0xA2, true},    {"pound", 0xA3, true},    {"yen", 0xA5, true},       {"micro", 0xB5, true},
    {"plusmn", 0xB1, true},  {"frac12", 0xBD, true},   {"eacute", 0xE9, true},    {"egrave", 0xE8, true},
    {"agrave", 0xE0, true},  {"ccedil", 0xE7, true},   {"uuml", 0xFC, true},      {"ouml", 0xF6, true},
    {"auml", 0xE4, true},    {"szlig", 0xDF, true},    {"euro", 0x20AC, false},   {"ndash", 0x2013, false},
    {"mdash", 0x2014, false}, {"hellip", 0x2026, false}, {"lsquo", 0x2018, false}, {"rsquo", 0x2019, false},
    {"ldquo", 0x201C, false}, {"rdquo", 0x201D, false}, {"trade", 0x2122, false}, {"bull", 0x2022, false},
};

static bool ascii_alnum(uint32_t c) { return c < 0x80 && (is_letter(c) || is_number(c)); }
static bool is_hex(uint32_t c) { return (c >= '0' && c <= '9') || ((c | 0x20) >= 'a' && (c | 0x20) <= 'f'); }

/* One pass of Python's html.unescape over in[0..n) into out (never longer).
 * Returns the new length. */
static size_t html_unescape(const uint32_t *in, size_t n, uint32_t *out) {
  size_t i = 0, k = 0;
  while (i < n) {
    if (in[i] != '&' || i + 1 >= n) {
      out[k++] = in[i++];
      continue;
    }
    size_t j = i + 1;
    if (in[j] == '#') {
      bool hex = j + 1 < n && (in[j + 1] == 'x' || in[j + 1] == 'X');
      size_t d = j + 1 + hex, e = d;
      uint64_t v = 0;
      while (e < n && (hex ? is_hex(in[e]) : (in[e] >= '0' && in[e] <= '9'))) {
        uint32_t c = in[e];
        uint32_t dv = c <= '9' ? c - '0' : (c | 0x20) - 'a' + 10;
        if (v <= 0x10FFFFull * 16) v = v * (hex ? 16 : 10) + dv;
        e++;
      }
      if (e == d) {
        out[k++] = in[i++];
        continue;
      }
      if (e < n && in[e] == ';') e++;
      if (v >= 0x80 && v <= 0x9F && cp1252[v - 0x80]) out[k++] = cp1252[v - 0x80];
      else if (v == 0 || (v >= 0xD800 && v <= 0xDFFF) || v > 0x10FFFF) out[k++] = 0xFFFD;
      else if (v == 0x0D) out[k++] = '\r';
      else if ((v >= 0x01 && v <= 0x08) || v == 0x0B || (v >= 0x0E && v <= 0x1F) || (v >= 0x7F && v <= 0x9F) ||
               (v >= 0xFDD0 && v <= 0xFDEF) || (v & 0xFFFE) == 0xFFFE)
        ; /* html.unescape drops these invalid code points */
      else out[k++] = (uint32_t)v;
      i = e;
      continue;
    }
    size_t e = j;
    while (e < n && e - j < 32 && ascii_alnum(in[e])) e++;
    bool semi = e < n && in[e] == ';';
    const struct entity *hit = NULL;
    size_t hit_len = 0;
    for (size_t q = 0; q < sizeof entities / sizeof entities[0]; q++) {
      size_t len = strlen(entities[q].name);
      if (len > e - j) continue;
      bool same = true;
      for (size_t c = 0; c < len && same; c++) same = in[j + c] == (uint32_t)entities[q].name[c];
      if (!same) continue;
      if (len == e - j && semi) { /* exact name with ';' */
        hit = &entities[q], hit_len = len + 1;
        break;
      }
      /* Without ';' only the legacy names, longest prefix first. */
      if (entities[q].legacy && len > hit_len) hit = &entities[q], hit_len = len;
    }
    if (!hit) {
      out[k++] = in[i++];
      continue;
    }
    out[k++] = hit->cp;
    i = j + hit_len;
  }
  return k;
}

static bool ftfy_control(uint32_t c) {
  return c <= 0x08 || c == 0x0B || (c >= 0x0E && c <= 0x1F) || c == 0x7F || (c >= 0x206A && c <= 0x206F) ||
         c == 0xFEFF || (c >= 0xFFF9 && c <= 0xFFFC);
}

/* Latin ligatures ftfy expands; returns the expansion length (0 = none). */
static size_t ligature(uint32_t c, uint32_t out[3]) {
  static const struct {
    uint32_t cp;
    const char *to;
  } lig[] = {{0x132, "IJ"}, {0x133, "ij"}, {0x1C7, "LJ"}, {0x1C8, "Lj"}, {0x1C9, "lj"}, {0x1CA, "NJ"},
             {0x1CB, "Nj"}, {0x1CC, "nj"}, {0x1F1, "DZ"}, {0x1F2, "Dz"}, {0x1F3, "dz"}, {0xFB00, "ff"},
             {0xFB01, "fi"}, {0xFB02, "fl"}, {0xFB03, "ffi"}, {0xFB04, "ffl"}, {0xFB06, "st"}};
  for (size_t i = 0; i < sizeof lig / sizeof lig[0]; i++)
    if (lig[i].cp == c) {
      size_t n = strlen(lig[i].to);
      for (size_t j = 0; j < n; j++) out[j] = (uint8_t)lig[i].to[j];
      return n;
    }
  if (c == 0xFB05) { /* long s + t */
    out[0] = 0x17F, out[1] = 't';
    return 2;
  }
  return 0;
}

/* ftfy's character fixes, in its order: C1 controls as Windows-1252,
 * ligatures, full-width forms, curly quotes, control characters. out needs
 * 3 * n entries. */
static size_t ftfy_fix(const uint32_t *in, size_t n, uint32_t *out) {
  size_t k = 0;
  for (size_t i = 0; i < n; i++) {
    uint32_t c = in[i];
    if (c >= 0x80 && c <= 0x9F && cp1252[c - 0x80]) c = cp1252[c - 0x80];
    uint32_t lig[3];
    size_t nl = ligature(c, lig);
    if (nl) {
      for (size_t j = 0; j < nl; j++) out[k++] = lig[j];
      continue;
    }
    if (c >= 0xFF01 && c <= 0xFF5E) c = c - 0xFF01 + 0x21;
    else if (c == 0x3000) c = ' ';
    if (c == 0x2BC || (c >= 0x2018 && c <= 0x201B)) c = '\'';
    else if (c >= 0x201C && c <= 0x201F) c = '"';
    if (ftfy_control(c)) continue;
    out[k++] = c;
  }
  return k;
}

/* basic_clean + whitespace_clean + lower(), as the reference composes them.
 * buf/tmp hold 3 * n + 1 code points. Returns the cleaned length. */
static size_t clean(uint32_t *buf, size_t n, uint32_t *tmp) {
  bool has_lt = false;
  for (size_t i = 0; i < n; i++) has_lt |= buf[i] == '<';
  /* ftfy unescapes HTML only in text that is not HTML-like itself. */
  if (!has_lt) n = html_unescape(buf, n, tmp), memcpy(buf, tmp, n * sizeof *buf);
  n = ftfy_fix(buf, n, tmp);
  n = html_unescape(tmp, n, buf);
  n = html_unescape(buf, n, tmp);
  /* strip + collapse whitespace runs to one space + strip */
  size_t k = 0;
  bool pending = false;
  for (size_t i = 0; i < n; i++) {
    if (is_space(tmp[i])) {
      pending = k > 0;
      continue;
    }
    if (pending) buf[k++] = ' ', pending = false;
    buf[k++] = tmp[i];
  }
  /* str.lower(): U+0130 is the one code point lowering to two; a capital
   * sigma lowers to the final form at the end of a word. */
  size_t m = 0;
  for (size_t i = 0; i < k; i++) {
    uint32_t c = buf[i];
    if (c == 0x130) {
      tmp[m++] = 'i', tmp[m++] = 0x307;
    } else if (c == 0x3A3) {
      bool final = i > 0 && is_letter(buf[i - 1]) && !(i + 1 < k && is_letter(buf[i + 1]));
      tmp[m++] = final ? 0x3C2 : 0x3C3;
    } else {
      tmp[m++] = to_lower(c);
    }
  }
  memcpy(buf, tmp, m * sizeof *buf);
  return m;
}

/* ---- BPE ---------------------------------------------------------------- */

/* Apply merges by rank to word[0..n); returns the new length. */
static size_t bpe(const struct vlff_tokenizer *t, int32_t *w, size_t n) {
  while (n > 1) {
    int32_t best_rank = INT32_MAX, a = -1, b = -1, id = -1;
    for (size_t i = 0; i + 1 < n; i++) {
      const struct pair_slot *p = pair_lookup(t, w[i], w[i + 1]);
      if (p && p->rank < best_rank) best_rank = p->rank, a = w[i], b = w[i + 1], id = p->id;
    }
    if (a < 0) break;
    size_t k = 0;
    for (size_t i = 0; i < n;) {
      if (i + 1 < n && w[i] == a && w[i + 1] == b) {
        w[k++] = id;
        i += 2;
      } else {
        w[k++] = w[i++];
      }
    }
    n = k;
  }
  return n;
}

static bool match_ascii(const uint32_t *s, size_t n, size_t i, const char *lit) {
  size_t len = strlen(lit);
  if (i + len > n) return false;
  for (size_t j = 0; j < len; j++)
    if (s[i + j] != (uint8_t)lit[j]) return false;
  return true;
}

long vlff_tokenizer_encode(const struct vlff_tokenizer *t, const char *text, size_t len, int32_t *ids, size_t cap,
                           char *err, size_t errlen) {
  if (!t || (!text && len)) {
    vlff_errf(err, errlen, "tokenizer: NULL argument");
    return -1;
  }
  if (len > VLFF_TOKENIZER_MAX_TEXT) {
    vlff_errf(err, errlen, "prompt: %zu bytes, longer than the limit of %d", len, VLFF_TOKENIZER_MAX_TEXT);
    return -1;
  }
  uint32_t *buf = malloc((3 * len + 1) * sizeof *buf);
  uint32_t *tmp = malloc((3 * len + 1) * sizeof *tmp);
  int32_t *word = malloc((4 * len + 1) * sizeof *word);
  long count = -1;
  if (!buf || !tmp || !word) {
    vlff_errf(err, errlen, "tokenizer: out of memory");
    goto out;
  }
  size_t bad = 0;
  long ncp = utf8_decode(text, len, buf, &bad);
  if (ncp < 0) {
    vlff_errf(err, errlen, "prompt: invalid UTF-8 at byte %zu", bad);
    goto out;
  }
  size_t n = clean(buf, (size_t)ncp, tmp);
  count = 0;
  /* CLIP's split regex, alternatives in its order:
   * <|startoftext|>|<|endoftext|>|'s|'t|'re|'ve|'m|'ll|'d|\p{L}+|\p{N}|[^\s\p{L}\p{N}]+ */
  for (size_t i = 0; i < n;) {
    uint32_t c = buf[i];
    if (is_space(c)) {
      i++;
      continue;
    }
    int32_t special = -1;
    size_t end = i + 1;
    if (match_ascii(buf, n, i, "<|startoftext|>")) special = VLFF_CLIP_SOT, end = i + 15;
    else if (match_ascii(buf, n, i, "<|endoftext|>")) special = VLFF_CLIP_EOT, end = i + 13;
    else if (c == '\'' && (match_ascii(buf, n, i, "'re") || match_ascii(buf, n, i, "'ve") || match_ascii(buf, n, i, "'ll")))
      end = i + 3;
    else if (c == '\'' && (match_ascii(buf, n, i, "'s") || match_ascii(buf, n, i, "'t") || match_ascii(buf, n, i, "'m") ||
                           match_ascii(buf, n, i, "'d")))
      end = i + 2;
    else if (is_letter(c))
      while (end < n && is_letter(buf[end])) end++;
    else if (!is_number(c))
      while (end < n && !is_space(buf[end]) && !is_letter(buf[end]) && !is_number(buf[end])) end++;
    if (special >= 0) {
      if ((size_t)count < cap) ids[count] = special;
      count++;
      i = end;
      continue;
    }
    size_t nb = 0;
    char last = 0;
    for (size_t j = i; j < end; j++) {
      char u[4];
      size_t ul = utf8_put(buf[j], u);
      for (size_t q = 0; q < ul; q++) word[nb++] = t->byte_id[(uint8_t)u[q]];
      last = u[ul - 1];
    }
    word[nb - 1] = t->byte_eow[(uint8_t)last]; /* the last symbol carries </w> */
    nb = bpe(t, word, nb);
    for (size_t j = 0; j < nb; j++, count++)
      if ((size_t)count < cap) ids[count] = word[j];
    i = end;
  }
out:
  free(buf);
  free(tmp);
  free(word);
  return count;
}

int vlff_tokenizer_context(const struct vlff_tokenizer *t, const char *text, int32_t out[VLFF_CLIP_CONTEXT],
                           char *err, size_t errlen) {
  if (!text) {
    vlff_errf(err, errlen, "prompt: NULL");
    return -1;
  }
  memset(out, 0, VLFF_CLIP_CONTEXT * sizeof *out);
  long n = vlff_tokenizer_encode(t, text, strlen(text), out + 1, VLFF_CLIP_CONTEXT - 2, err, errlen);
  if (n < 0) return -1;
  if (n > VLFF_CLIP_CONTEXT - 2) {
    memset(out, 0, VLFF_CLIP_CONTEXT * sizeof *out);
    vlff_errf(err, errlen, "prompt '%.40s': %ld tokens, more than the %d CLIP's context holds", text, n,
            VLFF_CLIP_CONTEXT - 2);
    return -1;
  }
  out[0] = VLFF_CLIP_SOT;
  out[n + 1] = VLFF_CLIP_EOT;
  return (int)n + 1;
}

/* ---- Loading ------------------------------------------------------------ */

static char *read_gz(const char *path, size_t *len, char *err, size_t errlen) {
  int fd = vlff_open_regular(path, err, errlen);
  if (fd < 0) return NULL;
  gzFile f = gzdopen(fd, "rb");
  if (!f) {
    close(fd);
    vlff_errf(err, errlen, "%s: cannot open BPE merges file: %s", path, errno ? strerror(errno) : "out of memory");
    return NULL;
  }
  size_t cap = 4u << 20, n = 0;
  char *buf = malloc(cap + 1);
  while (buf) {
    if (n == cap) {
      if (cap >= MAX_FILE_BYTES) {
        vlff_errf(err, errlen, "%s: BPE merges file decompresses to more than %u MiB: not a merges file", path,
                MAX_FILE_BYTES >> 20);
        goto fail;
      }
      char *nb = realloc(buf, 2 * cap + 1);
      if (!nb) break;
      buf = nb, cap *= 2;
    }
    int r = gzread(f, buf + n, (unsigned)(cap - n));
    if (r < 0) {
      int e;
      const char *m = gzerror(f, &e);
      vlff_errf(err, errlen, "%s: corrupt BPE merges file (gzip: %s)", path, m);
      goto fail;
    }
    if (r == 0) break;
    n += (size_t)r;
  }
  if (!buf) {
    vlff_errf(err, errlen, "%s: out of memory reading BPE merges file", path);
    gzclose(f);
    return NULL;
  }
  int e;
  const char *m = gzerror(f, &e);
  if (e != Z_OK) {
    vlff_errf(err, errlen, "%s: truncated or corrupt BPE merges file (gzip: %s)", path, m);
    goto fail;
  }
  gzclose(f);
  buf[n] = 0;
  *len = n;
  return buf;
fail:
  free(buf);
  gzclose(f);
  return NULL;
}

/* The 512 byte symbols (each byte alone and at a word's end), in the
 * reference's order: bytes '!'..'~', 0xA1..0xAC, 0xAE..0xFF stand for
 * themselves, then the other bytes as 256 + n. */
static int add_byte_symbols(struct vlff_tokenizer *t, const char *path, char *err, size_t errlen) {
  int32_t id = 0;
  uint32_t sym[256];
  int extra = 0;
  for (int pass = 0; pass < 2; pass++)
    for (int b = 0; b < 256; b++) {
      bool printable = (b >= '!' && b <= '~') || (b >= 0xA1 && b <= 0xAC) || (b >= 0xAE);
      if (printable != (pass == 0)) continue;
      sym[b] = printable ? (uint32_t)b : (uint32_t)(256 + extra++);
      t->byte_id[b] = id++;
    }
  for (int b = 0; b < 256; b++) {
    char u[4];
    size_t ul = utf8_put(sym[b], u);
    char *s = malloc(ul + 5), *s2 = malloc(ul + 5);
    if (!s || !s2) {
      free(s), free(s2);
      vlff_errf(err, errlen, "%s: out of memory", path);
      return -1;
    }
    memcpy(s, u, ul), s[ul] = 0;
    memcpy(s2, u, ul), memcpy(s2 + ul, "</w>", 5);
    t->strings[t->byte_id[b]] = s;
    t->strings[t->byte_id[b] + 256] = s2;
  }
  for (int32_t i = 0; i < 512; i++) str_insert(t, i);

  return 0;
}

/* The merges file's header line, then NUM_MERGES lines "a b" of known
 * symbols, each adding the symbol ab. */
static int add_merges(struct vlff_tokenizer *t, const char *text, size_t len, const char *path, char *err,
                      size_t errlen) {
  const char *p = strchr(text, '\n');
  if (!p || !strstr(text, "#version") || (size_t)(p - text) > 200 || memchr(text, 0, len)) {
    vlff_errf(err, errlen, "%s:1: expected a BPE merges header ('#version: ...'), not a CLIP merges file", path);
    return -1;
  }
  p++;
  for (int r = 0; r < NUM_MERGES; r++) {
    int line = r + 2;
    const char *eol = strchr(p, '\n');
    size_t ll = eol ? (size_t)(eol - p) : strlen(p);
    if (!ll && !eol) {
      vlff_errf(err, errlen, "%s: only %d merges, expected %d (truncated file?)", path, r, NUM_MERGES);
      return -1;
    }
    size_t bad_at;
    char a[256], b[256];
    size_t sp = 0;
    while (sp < ll && p[sp] != ' ') sp++;
    if (sp == 0 || sp >= ll - 1 || sp >= sizeof a || ll - sp - 1 >= sizeof b || memchr(p + sp + 1, ' ', ll - sp - 1)) {
      vlff_errf(err, errlen, "%s:%d: expected a merge 'a b' (two symbols, one space), got '%.*s'", path, line,
              (int)(ll > 60 ? 60 : ll), p);
      return -1;
    }
    memcpy(a, p, sp), a[sp] = 0;
    memcpy(b, p + sp + 1, ll - sp - 1), b[ll - sp - 1] = 0;
    uint32_t *cps = malloc((ll + 1) * sizeof *cps);
    long ok = cps ? utf8_decode(p, ll, cps, &bad_at) : -1;
    free(cps);
    if (ok < 0) {
      vlff_errf(err, errlen, "%s:%d: invalid UTF-8 in merge", path, line);
      return -1;
    }
    int32_t ia = str_lookup(t, a, sp), ib = str_lookup(t, b, ll - sp - 1);
    if (ia < 0 || ib < 0) {
      vlff_errf(err, errlen, "%s:%d: merge of unknown symbol '%s' (corrupt merges file)", path, line, ia < 0 ? a : b);
      return -1;
    }
    size_t nl = sp + (ll - sp - 1);
    char *s = malloc(nl + 1);
    if (!s) {
      vlff_errf(err, errlen, "%s: out of memory", path);
      return -1;
    }
    memcpy(s, a, sp), memcpy(s + sp, b, ll - sp - 1), s[nl] = 0;
    t->strings[512 + r] = s;
    str_insert(t, 512 + r);
    p = eol ? eol + 1 : p + ll;
  }
  t->strings[VLFF_CLIP_SOT] = strdup("<|startoftext|>");
  t->strings[VLFF_CLIP_EOT] = strdup("<|endoftext|>");
  if (!t->strings[VLFF_CLIP_SOT] || !t->strings[VLFF_CLIP_EOT]) {
    vlff_errf(err, errlen, "%s: out of memory", path);
    return -1;
  }
  str_insert(t, VLFF_CLIP_SOT);
  str_insert(t, VLFF_CLIP_EOT);
  return 0;
}

/* Resolves every byte symbol and merge through the string table, so that
 * repeated strings behave as in the reference (the last id wins), and
 * fills the merge ranks. */
static void resolve_merges(struct vlff_tokenizer *t, const char *text) {
  for (int b = 0; b < 256; b++) {
    const char *s = t->strings[t->byte_id[b]], *s2 = t->strings[t->byte_id[b] + 256];
    t->byte_eow[b] = str_lookup(t, s2, strlen(s2));
    t->byte_id[b] = str_lookup(t, s, strlen(s));
  }
  const char *p = strchr(text, '\n') + 1;
  for (int r = 0; r < NUM_MERGES; r++) {
    const char *eol = strchr(p, '\n');
    size_t ll = eol ? (size_t)(eol - p) : strlen(p);
    size_t sp = (size_t)((const char *)memchr(p, ' ', ll) - p);
    int32_t ia = str_lookup(t, p, sp), ib = str_lookup(t, p + sp + 1, ll - sp - 1);
    const char *s = t->strings[512 + r];
    pair_insert(t, ia, ib, r, str_lookup(t, s, strlen(s)));
    p = eol ? eol + 1 : p + ll;
  }
}

struct vlff_tokenizer *vlff_tokenizer_open(const char *path, char *err, size_t errlen) {
  if (!path || !*path) {
    vlff_errf(err, errlen, "vlm.bpe_vocab: no BPE merges file configured");
    return NULL;
  }
  size_t len = 0;
  char *text = read_gz(path, &len, err, errlen);
  if (!text) return NULL;
  struct vlff_tokenizer *t = calloc(1, sizeof *t);
  if (!t) {
    vlff_errf(err, errlen, "%s: out of memory", path);
    free(text);
    return NULL;
  }
  if (add_byte_symbols(t, path, err, errlen) || add_merges(t, text, len, path, err, errlen)) {
    free(text);
    vlff_tokenizer_close(t);
    return NULL;
  }
  resolve_merges(t, text);
  free(text);
  return t;
}

void vlff_tokenizer_close(struct vlff_tokenizer *t) {
  if (!t) return;
  for (int i = 0; i < VLFF_CLIP_VOCAB; i++) free(t->strings[i]);
  free(t);
}
