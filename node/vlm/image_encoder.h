/*
 * vlff_image_encoder: dense vision-language features from an ONNX model run
 * by OpenCV DNN, and vlff_image_worker, which runs it on its own thread.
 *
 * Model contract: input [1,3,H,W] float (H, W = vlm.input_height/width),
 * output [1,D,h,w] float with D = field.feature_dim (LSeg exported by
 * node/vlm/export/export_lseg.py, or any model with that contract).
 * Preprocessing: the RGB8 frame is resized to W x H (area averaging when
 * shrinking, bilinear otherwise; aspect ratio is not kept), scaled to [0,1],
 * normalised per channel with vlm.mean/vlm.std (given in R,G,B order) and
 * fed as RGB, or BGR when vlm.bgr is set. Output: IEEE float16 [h][w][D],
 * each pixel L2-normalised when vlm.normalize is set.
 *
 * Contract
 *  - int functions return 0 on success, -1 on error with one line in err
 *    naming the model file and what was wrong.
 *  - vlff_image_encoder_open() validates the model before returning: it runs
 *    a probe inference and checks rank, shape, D against field.feature_dim
 *    and finiteness, so a wrong or corrupt model fails at start-up.
 *  - An encoder is used by one thread at a time. A worker owns its encoder;
 *    its submit/poll/stats calls may come from any thread and never block
 *    on inference.
 */
#ifndef VLFF_IMAGE_ENCODER_H
#define VLFF_IMAGE_ENCODER_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "config.h"

struct vlff_image_encoder;

/* From the vlm section; feature_dim is the D the model must give. */
struct vlff_image_encoder *vlff_image_encoder_open(const struct vlff_cfg_vlm *vlm, int feature_dim, char *err,
                                                   size_t errlen);
void vlff_image_encoder_close(struct vlff_image_encoder *enc);

/* Output geometry: D, h, w. */
void vlff_image_encoder_shape(const struct vlff_image_encoder *enc, int *dim, int *height, int *width);

/* Encode one RGB8 frame (rows stride bytes apart) into out, which holds
 * h * w * D float16 values. A frame with non-finite output is an error. */
int vlff_image_encoder_run(struct vlff_image_encoder *enc, const uint8_t *rgb, int width, int height, size_t stride,
                           uint16_t *out, char *err, size_t errlen);

/* ---- worker thread ------------------------------------------------------ */

struct vlff_image_worker;

struct vlff_image_worker_stats {
  uint64_t submitted, encoded, failed;
  uint64_t dropped_frames;   /* pending frames replaced by newer ones */
  uint64_t dropped_results;  /* results nobody polled before newer ones */
};

/* Start a worker that owns enc (closed by vlff_image_worker_stop, also on
 * failure here). depth: frames waiting at most (>= 1). */
struct vlff_image_worker *vlff_image_worker_start(struct vlff_image_encoder *enc, int depth, char *err,
                                                  size_t errlen);
/* Stop the thread, drop what is pending, free everything. */
void vlff_image_worker_stop(struct vlff_image_worker *w);

/* Queue a copy of a frame. Never blocks: with the queue full the oldest
 * pending frame is dropped (keyframes want the newest). Returns 0, or -1
 * for an invalid frame. */
int vlff_image_worker_submit(struct vlff_image_worker *w, uint64_t frame_id, const uint8_t *rgb, int width,
                             int height, size_t stride);

/* Take the oldest finished result: returns 1 and fills *frame_id and out
 * (h * w * D float16), 0 when none is ready, -1 when that frame failed (its
 * id in *frame_id, the reason in err). */
int vlff_image_worker_poll(struct vlff_image_worker *w, uint64_t *frame_id, uint16_t *out, char *err,
                           size_t errlen);

void vlff_image_worker_stats(struct vlff_image_worker *w, struct vlff_image_worker_stats *st);

#endif
