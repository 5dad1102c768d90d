/*
 * Volume rendering (the paper's eq. 1-2): w_s = T_s (1 - exp(-sigma_s delta_s)),
 * T_s = prod_{j<s} (1 - alpha_j); any rendered quantity is sum_s w_s v_s.
 *
 * Backward for all channels at once: with e_s = dL/dO . v_s (the caller folds
 * colour, depth and feature gradients into that one scalar per sample),
 *   dL/dsigma_k = delta_k (T_{k+1} e_k - sum_{s>k} w_s e_s)
 * which needs one suffix sum per ray. Rays stop once T < VLFF_T_MIN: the rest
 * of the ray contributes less than that to any output.
 */
#include <math.h>

#include "field_internal.h"

int vlff_render_weights(const float *sigma, const float *delta, int ns, float *w, float *trans) {
  float t = 1.0f;
  int s = 0;
  for (; s < ns; s++) {
    float keep = expf(-sigma[s] * delta[s]);
    trans[s] = t;
    w[s] = t * (1.0f - keep);
    t *= keep;
    if (t < VLFF_T_MIN) {
      s++;
      break;
    }
  }
  for (int r = s; r < ns; r++) {
    w[r] = 0.0f;
    trans[r] = 0.0f;
  }
  return s;
}

void vlff_render_backward(const float *w, const float *trans, const float *sigma, const float *delta,
                          const float *e, int ns, float *dsigma) {
  (void)sigma;
  float suffix = 0.0f;
  for (int k = ns - 1; k >= 0; k--) {
    float tnext = trans[k] - w[k];
    dsigma[k] = delta[k] * (tnext * e[k] - suffix);
    suffix += w[k] * e[k];
  }
}
