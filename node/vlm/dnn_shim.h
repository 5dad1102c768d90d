/*
 * vlff_dnn: the one C++ file between vlff's C code and OpenCV's DNN module.
 *
 * Loads an ONNX model with OpenCV 4.6's importer, runs it on a float
 * input blob and hands back the outputs as plain float arrays + shapes.
 * Layer fusion is always off: with it on, OpenCV 4.6 computes scaled
 * dot-product attention wrongly (see docs/vlm.md).
 *
 * Contract
 *  - Functions returning int give 0 (or a count) on success, -1 on error
 *    with one line in err naming the model file and what failed. No C++
 *    exception ever crosses this header.
 *  - vlff_dnn_open() returns an object the caller frees with
 *    vlff_dnn_close(). Output arrays returned by vlff_dnn_run() belong to
 *    the object and stay valid until the next run or close.
 *  - One thread at a time per object; distinct objects are independent.
 */
#ifndef VLFF_DNN_SHIM_H
#define VLFF_DNN_SHIM_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define VLFF_DNN_MAX_DIMS 6
#define VLFF_DNN_MAX_OUTPUTS 4

struct vlff_dnn;

struct vlff_tensor {
  int ndim;
  int shape[VLFF_DNN_MAX_DIMS];
  size_t count;       /* product of shape */
  const float *data;  /* owned by the vlff_dnn */
};

/* Load path. want_cuda asks for OpenCV's CUDA backend; *used_cuda (may be
 * NULL) tells whether it was available and chosen, else the CPU runs it. */
struct vlff_dnn *vlff_dnn_open(const char *path, bool want_cuda, bool *used_cuda, char *err, size_t errlen);
void vlff_dnn_close(struct vlff_dnn *net);

/* Run on one input of ndim dims (NCHW for images; [1,77] token ids as
 * floats for the text model). Returns the number of outputs written to
 * out[0..max_out), in the model's output order. */
int vlff_dnn_run(struct vlff_dnn *net, const float *input, const int *shape, int ndim, struct vlff_tensor *out,
                 int max_out, char *err, size_t errlen);

/* OpenCV's own worker threads for every network in the process (it is a
 * process-wide setting): n > 0 threads, 0 = run sequentially (no pool), for
 * sharing cores with the learner. 0, or -1 with err. */
int vlff_dnn_set_threads(int n, char *err, size_t errlen);

/* Resize a packed 8-bit image (channels 1..4) with bilinear interpolation,
 * area averaging when shrinking. 0 or -1 with err. */
int vlff_dnn_resize(const uint8_t *src, int w, int h, int channels, uint8_t *dst, int dw, int dh, char *err,
                    size_t errlen);

#ifdef __cplusplus
}
#endif
#endif
