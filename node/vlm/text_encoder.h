/*
 * vlff_text_encoder: prompt -> L2-normalised CLIP text embedding.
 *
 * The prompt goes through prompts.template ("{}" replaced by the prompt),
 * the C tokenizer (vlm.bpe_vocab), a lookup in the token-embedding table
 * (vlm.text_model + ".tokemb", written by export_clip_text.py) and the text
 * transformer (vlm.text_model, run by OpenCV DNN), whose output row at the
 * end-of-text token is the embedding. Results are cached per prompt.
 *
 * Contract
 *  - int functions return 0 on success, -1 on error with one line in err
 *    naming the file or prompt and what was wrong.
 *  - vlff_text_encoder_open() validates everything up front: merges file,
 *    token table (size, finiteness), and a probe inference whose output
 *    must be [1,77,D] with D = field.feature_dim.
 *  - One thread at a time per encoder (it owns a network and a cache).
 */
#ifndef VLFF_TEXT_ENCODER_H
#define VLFF_TEXT_ENCODER_H

#include <stddef.h>

#include "config.h"

#define VLFF_TEXT_CACHE 256

struct vlff_text_encoder;

/* From the vlm section (text_model, bpe_vocab, cuda); templ is the prompt
 * template (prompts.templ), feature_dim the D the model must give. */
struct vlff_text_encoder *vlff_text_encoder_open(const struct vlff_cfg_vlm *vlm, const char *templ, int feature_dim,
                                                 char *err, size_t errlen);
void vlff_text_encoder_close(struct vlff_text_encoder *enc);

int vlff_text_encoder_dim(const struct vlff_text_encoder *enc);

/* Embed one prompt into out[D] (unit length). A prompt holding CLIP's
 * special tokens, invalid UTF-8 or more than 75 tokens is refused. */
int vlff_text_encoder_encode(struct vlff_text_encoder *enc, const char *prompt, float *out, char *err,
                             size_t errlen);

/* Cache hits and misses since open. */
void vlff_text_encoder_cache_stats(const struct vlff_text_encoder *enc, long *hits, long *misses);

#endif
