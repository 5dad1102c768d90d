/*
 * vlff_tokenizer: CLIP's byte-pair-encoding tokenizer, in C.
 *
 * Turns a prompt into the token ids CLIP's text transformer (and LSeg's)
 * was trained on, reproducing openai/CLIP's SimpleTokenizer: text cleaned
 * (the parts of ftfy.fix_text and html.unescape that plain prompts meet,
 * see docs/vlm.md), whitespace collapsed, lower-cased
 * as Python's str.lower(), split by CLIP's regex, UTF-8 bytes mapped to
 * CLIP's byte symbols, merges applied by rank, "</w>" ending each word.
 *
 * Contract
 *  - Functions returning int give >= 0 on success, -1 on error with one line
 *    in err (when err is not NULL) naming what was wrong and where.
 *  - vlff_tokenizer_open() reads the gzip merges file (bpe_simple_vocab_16e6
 *    .txt.gz) and validates it: a missing, corrupt, truncated or short file
 *    is refused with the path and line in the message.
 *  - The tokenizer is immutable after open: every other call may run from
 *    any number of threads at once. The caller owns it and frees it with
 *    vlff_tokenizer_close().
 *  - Prompts must be valid UTF-8 of at most VLFF_TOKENIZER_MAX_TEXT bytes;
 *    anything else is refused, never guessed at.
 */
#ifndef VLFF_TOKENIZER_H
#define VLFF_TOKENIZER_H

#include <stddef.h>
#include <stdint.h>

#define VLFF_CLIP_SOT 49406
#define VLFF_CLIP_EOT 49407
#define VLFF_CLIP_VOCAB 49408
#define VLFF_CLIP_CONTEXT 77
#define VLFF_TOKENIZER_MAX_TEXT 16384

struct vlff_tokenizer;

struct vlff_tokenizer *vlff_tokenizer_open(const char *merges_gz_path, char *err, size_t errlen);
void vlff_tokenizer_close(struct vlff_tokenizer *tok);

/* Token ids of text (len bytes, no NUL needed), without start/end tokens.
 * Writes at most cap ids and returns the total count, which may exceed cap
 * (call again with a larger buffer). */
long vlff_tokenizer_encode(const struct vlff_tokenizer *tok, const char *text, size_t len, int32_t *ids,
                           size_t cap, char *err, size_t errlen);

/* The model input: [SOT] + ids + [EOT], zero-padded to 77. Returns the
 * position of EOT; a prompt longer than 75 tokens is an error (CLIP's
 * default, no silent truncation). */
int vlff_tokenizer_context(const struct vlff_tokenizer *tok, const char *text,
                           int32_t out[VLFF_CLIP_CONTEXT], char *err, size_t errlen);

#endif
