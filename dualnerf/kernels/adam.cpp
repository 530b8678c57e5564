#include "kernels.h"

using namespace dualnerf;

// ---- Adam for the trainer (dualnerf.optim): one pass per tensor, optionally skipping zero gradients ----
//
// The same rounded float operations, in the same order, as dualnerf.optim.adam_reference (built with
// -ffp-contract=off, so no fused multiply-adds), hence bit-for-bit its result:
//   m = b1 m + (1 - b1) g;  v = b2 v + (1 - b2) g g;  p = p - step_size (m / (sqrt(v) / bc2_sqrt + eps)).
// skip_zero: entries whose gradient is exactly 0 keep p, m and v (instant-NGP's rule for feature tables:
// a batch touches a small part of a table, and the dense update of every entry was memory-bound).
void check_adam_tensors(const at::Tensor& param, const at::Tensor& grad, const at::Tensor& exp_avg,
                        const at::Tensor& exp_avg_sq) {
  for (const auto* t : {&param, &grad, &exp_avg, &exp_avg_sq})
    TORCH_CHECK(t->scalar_type() == at::kFloat && t->device().is_cpu() && t->numel() == param.numel(),
                "adam_step: float32 CPU tensors of one size expected");
  // The optimiser state is allocated like the parameter (same strides); the element-wise update only
  // needs all four to share one memory layout.
  TORCH_CHECK(param.strides() == grad.strides() && param.strides() == exp_avg.strides() &&
                  param.strides() == exp_avg_sq.strides() && param.is_non_overlapping_and_dense(),
              "adam_step: parameter, gradient and state must share one dense memory layout");
}

struct AdamUpdate {
  float b1, b2, one_minus_b1, one_minus_b2, step, bc2, eps;
  AdamUpdate(double beta1, double beta2, double step_size, double bias_correction2_sqrt, double e)
      : b1(static_cast<float>(beta1)), b2(static_cast<float>(beta2)), one_minus_b1(static_cast<float>(1.0 - beta1)),
        one_minus_b2(static_cast<float>(1.0 - beta2)), step(static_cast<float>(step_size)),
        bc2(static_cast<float>(bias_correction2_sqrt)), eps(static_cast<float>(e)) {}
  inline void operator()(float& p, float g, float& m, float& v) const {
    m = b1 * m + one_minus_b1 * g;
    v = b2 * v + one_minus_b2 * g * g;
    p = p - step * (m / (std::sqrt(v) / bc2 + eps));
  }
};

void adam_step(at::Tensor param, at::Tensor grad, at::Tensor exp_avg, at::Tensor exp_avg_sq, double beta1,
               double beta2, double step_size, double bias_correction2_sqrt, double eps, bool skip_zero) {
  check_adam_tensors(param, grad, exp_avg, exp_avg_sq);
  const AdamUpdate update(beta1, beta2, step_size, bias_correction2_sqrt, eps);
  float* p = param.data_ptr<float>();
  const float* g = grad.data_ptr<float>();
  float* m = exp_avg.data_ptr<float>();
  float* v = exp_avg_sq.data_ptr<float>();
  parallel_for(0, param.numel(), 1 << 16, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i)
      if (!skip_zero || g[i] != 0.0f) update(p[i], g[i], m[i], v[i]);
  });
}

#ifdef DUALNERF_HAVE_AVX512
// One chunk of 16 entries as AdamUpdate does them one by one: the same separately rounded mul, add, sqrt
// and div (no fused multiply-add), so the same bits; entries with a zero gradient keep p, m and v
// (NaN gradients update, as `g != 0` is true for NaN). The gradients are zeroed for the next step.
__attribute__((target("avx512f"))) void adam_chunk_avx512(const AdamUpdate& u, float* p, float* g, float* m, float* v) {
  const __m512 grad = _mm512_loadu_ps(g);
  const __mmask16 nonzero = _mm512_cmp_ps_mask(grad, _mm512_setzero_ps(), _CMP_NEQ_UQ);
  if (nonzero) {
    const __m512 m_new = _mm512_add_ps(_mm512_mul_ps(_mm512_set1_ps(u.b1), _mm512_loadu_ps(m)),
                                       _mm512_mul_ps(_mm512_set1_ps(u.one_minus_b1), grad));
    const __m512 v_new = _mm512_add_ps(_mm512_mul_ps(_mm512_set1_ps(u.b2), _mm512_loadu_ps(v)),
                                       _mm512_mul_ps(_mm512_mul_ps(_mm512_set1_ps(u.one_minus_b2), grad), grad));
    const __m512 denom = _mm512_add_ps(_mm512_div_ps(_mm512_sqrt_ps(v_new), _mm512_set1_ps(u.bc2)),
                                       _mm512_set1_ps(u.eps));
    const __m512 p_new = _mm512_sub_ps(_mm512_loadu_ps(p), _mm512_mul_ps(_mm512_set1_ps(u.step),
                                                                         _mm512_div_ps(m_new, denom)));
    _mm512_mask_storeu_ps(m, nonzero, m_new);
    _mm512_mask_storeu_ps(v, nonzero, v_new);
    _mm512_mask_storeu_ps(p, nonzero, p_new);
  }
  _mm512_storeu_ps(g, _mm512_setzero_ps());
}
#endif

constexpr int64_t kAdamAhead = 64;     // chunks (of 16 values: one cache line) prefetched ahead; 4-256
                                       // measured, 64-256 alike, ~1.2x the pass without

// adam_step with skip_zero on the touched chunks of a TableGradients buffer only (an untouched chunk's
// gradients are all zero, so skip_zero would leave it as it is anyway: the same bits as adam_step), then
// zeroes those gradients and flags for the next backward.
void adam_step_touched(at::Tensor param, at::Tensor grad, at::Tensor touched, at::Tensor exp_avg,
                       at::Tensor exp_avg_sq, double beta1, double beta2, double step_size,
                       double bias_correction2_sqrt, double eps) {
  check_adam_tensors(param, grad, exp_avg, exp_avg_sq);
  const int64_t n = param.numel();
  TORCH_CHECK(touched.scalar_type() == at::kByte && touched.is_contiguous() &&
                  touched.numel() == (n + kTouchChunk - 1) / kTouchChunk,
              "adam_step_touched: one uint8 flag per ", kTouchChunk, " values expected");
  const AdamUpdate update(beta1, beta2, step_size, bias_correction2_sqrt, eps);
  float* p = param.data_ptr<float>();
  float* g = grad.data_ptr<float>();
  float* m = exp_avg.data_ptr<float>();
  float* v = exp_avg_sq.data_ptr<float>();
  uint8_t* flags = touched.data_ptr<uint8_t>();
  const bool vec = avx512_available();
  parallel_for(0, touched.numel(), 1 << 12, [&](int64_t chunk_begin, int64_t chunk_end) {
    for (int64_t c = chunk_begin; c < chunk_end; ++c) {
      // The touched chunks are scattered over tables larger than the caches and each waits on four
      // lines (p, g, m, v): those of the chunk kAdamAhead further on are requested now.
      const int64_t ahead = c + kAdamAhead;
      if (ahead < chunk_end && flags[ahead]) {
        const int64_t at = ahead * kTouchChunk;
        __builtin_prefetch(p + at);        // prefetcht0 (the build targets no prefetch-for-write)
        __builtin_prefetch(g + at);
        __builtin_prefetch(m + at);
        __builtin_prefetch(v + at);
      }
      if (!flags[c]) continue;
      const int64_t begin = c * kTouchChunk, end = std::min(n, begin + kTouchChunk);
#ifdef DUALNERF_HAVE_AVX512
      if (vec && end - begin == kTouchChunk) {
        adam_chunk_avx512(update, p + begin, g + begin, m + begin, v + begin);
        flags[c] = 0;
        continue;
      }
#endif
      for (int64_t i = begin; i < end; ++i) {
        if (g[i] != 0.0f) update(p[i], g[i], m[i], v[i]);
        g[i] = 0.0f;
      }
      flags[c] = 0;
    }
  });
}

