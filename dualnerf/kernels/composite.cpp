#include "kernels.h"

using namespace dualnerf;

// ---- A render's packing and compositing (dualnerf.rendering.render_rays without autograd) ----
//
// occupied_samples: the occupied samples' points x = o + t d (the same float operations as the torch
// code, so the same bits), their flat index r * S + s in increasing order, their ray, and each ray's first
// entry (R + 1 offsets). composite_rays: the colour and opacity of each ray from its evaluated samples,
// the formulas of rendering.composite with decode_density / decode_color, summed per ray in sample order;
// torch's exp and sums round differently, so the two agree to float32 rounding (tests/test_render_kernels.py);
// the AVX-512, AVX2 and portable paths give the same bits.
std::vector<at::Tensor> occupied_samples(at::Tensor origins, at::Tensor dirs, at::Tensor t,
                                         at::Tensor mask) {
  for (const auto* x : {&origins, &dirs, &t})
    TORCH_CHECK(x->scalar_type() == at::kFloat && x->device().is_cpu(), "occupied_samples: float32 CPU tensors");
  TORCH_CHECK(mask.scalar_type() == at::kBool && mask.sizes() == t.sizes() && t.dim() == 2 &&
                  origins.size(0) == t.size(0) && dirs.sizes() == origins.sizes() && origins.size(1) == 3,
              "occupied_samples: origins, dirs (R, 3), t and mask (R, S)");
  origins = origins.contiguous();
  dirs = dirs.contiguous();
  t = t.contiguous();
  mask = mask.contiguous();
  const int64_t n_rays = t.size(0), S = t.size(1);
  auto starts = t.new_empty({n_rays + 1}, at::kLong);
  int64_t* st = starts.data_ptr<int64_t>();
  const bool* mp = mask.data_ptr<bool>();
  st[0] = 0;
  for (int64_t r = 0; r < n_rays; ++r) {
    int64_t count = 0;
    for (int64_t s = 0; s < S; ++s) count += mp[r * S + s];
    st[r + 1] = st[r] + count;
  }
  const int64_t m = st[n_rays];
  auto x = t.new_empty({m, 3});
  auto flat = t.new_empty({m}, at::kLong);
  auto ray = t.new_empty({m}, at::kLong);
  const float *op = origins.data_ptr<float>(), *dp = dirs.data_ptr<float>(), *tp = t.data_ptr<float>();
  float* xp = x.data_ptr<float>();
  int64_t *fp = flat.data_ptr<int64_t>(), *rp = ray.data_ptr<int64_t>();
  parallel_for(0, n_rays, 256, [&](int64_t begin, int64_t end) {
    for (int64_t r = begin; r < end; ++r) {
      int64_t j = st[r];
      for (int64_t s = 0; s < S; ++s) {
        if (!mp[r * S + s]) continue;
        const float ts = tp[r * S + s];
        for (int a = 0; a < 3; ++a) xp[3 * j + a] = op[3 * r + a] + ts * dp[3 * r + a];
        fp[j] = r * S + s;
        rp[j] = r;
        ++j;
      }
    }
  });
  return {x, flat, ray, starts};
}

struct RayComposite {
  const float *hs, *hc, *delta, *bg;
  const int64_t *fp, *st;
  int64_t S;
  float clamp;
  float *color, *opacity;
};

// One ray in the order of rendering.composite: sigma = exp(min(h, clamp)) for evaluated samples (0 for the
// others), tau = sigma delta, alpha = 1 - exp(-tau), T = exp(-(cumsum(tau) - tau)) with the cumulative sum
// in double as torch's, w = T alpha; colour = sum w sigmoid(h_color) + (1 - sum w) background.
void composite_ray_scalar(const RayComposite& c, int64_t r) {
  double cumulative = 0.0;
  float weight_sum = 0.0f, rgb[3] = {0.0f, 0.0f, 0.0f};
  int64_t j = c.st[r];
  const int64_t stop = c.st[r + 1], S = c.S;
  for (int64_t s = 0; s < S; ++s) {
    const bool evaluated = j < stop && c.fp[j] == r * S + s;
    const float sigma = evaluated ? exp_scalar(std::min(c.hs[j], c.clamp)) : 0.0f;
    const float tau = sigma * c.delta[r * S + s];
    const float alpha = 1.0f - exp_scalar(-tau);
    cumulative += static_cast<double>(tau);
    const float w = exp_scalar(tau - static_cast<float>(cumulative)) * alpha;
    weight_sum += w;
    if (evaluated) {
      for (int a = 0; a < 3; ++a) rgb[a] += w * (1.0f / (1.0f + exp_scalar(-c.hc[3 * j + a])));
      ++j;
    }
  }
  c.opacity[r] = weight_sum;
  for (int a = 0; a < 3; ++a) c.color[3 * r + a] = rgb[a] + (1.0f - weight_sum) * c.bg[3 * r + a];
}

// The sequential sums of the vector code (composite_ray_avx512, composite_ray_avx2), in sample order as in
// composite_ray_scalar: w[s] = tau[s] - cumsum(tau)[s] (the sum in double), exponentiated by the caller.
inline void transmittance_exponents(const float* tau, float* w, int64_t S) {
  double cumulative = 0.0;
  for (int64_t s = 0; s < S; ++s) {
    cumulative += static_cast<double>(tau[s]);
    w[s] = tau[s] - static_cast<float>(cumulative);
  }
}

// Ray r's opacity (its weights w summed in sample order) and colour (w times the sigmoid colours rgb of its
// evaluated samples, 3 each, plus the background's share), as composite_ray_scalar sums them.
inline void finish_ray(const RayComposite& c, int64_t r, const float* w, const float* rgb) {
  const int64_t S = c.S, first = c.st[r], stop = c.st[r + 1];
  float opacity = 0.0f;
  for (int64_t s = 0; s < S; ++s) opacity += w[s];
  float out[3] = {0.0f, 0.0f, 0.0f};
  for (int64_t j = first; j < stop; ++j) {
    const float weight = w[c.fp[j] - r * S];
    for (int a = 0; a < 3; ++a) out[a] += weight * rgb[3 * (j - first) + a];
  }
  c.opacity[r] = opacity;
  for (int a = 0; a < 3; ++a) c.color[3 * r + a] = out[a] + (1.0f - opacity) * c.bg[3 * r + a];
}

#ifdef DUALNERF_HAVE_AVX512
// composite_ray_scalar's operations 16 samples at a time (exp16 is exp_scalar's vector form; the
// cumulative sum and the opacity stay sequential sums in sample order): the same bits.
// buf: scratch of 4 x S (rounded up to 16) + 3 x S floats.
__attribute__((target("avx512f"))) void composite_ray_avx512(const RayComposite& c, int64_t r, float* buf) {
  const int64_t S = c.S, S_pad = (S + kLanes - 1) / kLanes * kLanes, first = c.st[r], stop = c.st[r + 1];
  float *h = buf, *tau = buf + S_pad, *alpha = buf + 2 * S_pad, *w = buf + 3 * S_pad, *rgb = buf + 4 * S_pad;
  __mmask16 evaluated[64] = {};      // S <= 1024 (checked by the caller)
  for (int64_t j = first; j < stop; ++j) {
    const int64_t s = c.fp[j] - r * S;
    h[s] = std::min(c.hs[j], c.clamp);
    evaluated[s / kLanes] |= static_cast<__mmask16>(1u << (s % kLanes));
  }
  const __m512 one = _mm512_set1_ps(1.0f);
  for (int64_t s = 0; s < S_pad; s += kLanes) {
    const int64_t left = S - s;
    const __mmask16 lanes = first_lanes(left);
    const __mmask16 ev = evaluated[s / kLanes];
    const __m512 sigma = _mm512_maskz_mov_ps(ev, exp16(_mm512_maskz_loadu_ps(ev, h + s)));
    const __m512 t = _mm512_mul_ps(sigma, _mm512_maskz_loadu_ps(lanes, c.delta + r * S + s));
    _mm512_storeu_ps(tau + s, t);
    _mm512_storeu_ps(alpha + s, _mm512_sub_ps(one, exp16(_mm512_sub_ps(_mm512_setzero_ps(), t))));
  }
  transmittance_exponents(tau, w, S);
  for (int64_t s = 0; s < S_pad; s += kLanes) {
    const int64_t left = S - s;
    const __mmask16 lanes = first_lanes(left);
    _mm512_storeu_ps(w + s, _mm512_maskz_mul_ps(lanes, exp16(_mm512_loadu_ps(w + s)), _mm512_loadu_ps(alpha + s)));
  }
  const int64_t n_color = 3 * (stop - first);
  for (int64_t k = 0; k < n_color; k += kLanes) {
    const int64_t left = n_color - k;
    const __mmask16 lanes = first_lanes(left);
    const __m512 x = _mm512_maskz_loadu_ps(lanes, c.hc + 3 * first + k);
    _mm512_mask_storeu_ps(rgb + k, lanes,
                          _mm512_div_ps(one, _mm512_add_ps(one, exp16(_mm512_sub_ps(_mm512_setzero_ps(), x)))));
  }
  finish_ray(c, r, w, rgb);
}
#endif

#ifdef DUALNERF_HAVE_AVX2
// composite_ray_avx512's operations 8 samples at a time, for builds with the AVX2 flags on CPUs without
// AVX-512 (masked lanes as zeros, as there): the same bits. buf: scratch of 5 x S (rounded up to 8) + 3 x S
// floats.
void composite_ray_avx2(const RayComposite& c, int64_t r, float* buf) {
  const int64_t S = c.S, S_pad = (S + 7) / 8 * 8, first = c.st[r], stop = c.st[r + 1];
  float *h = buf, *tau = buf + S_pad, *alpha = buf + 2 * S_pad, *w = buf + 3 * S_pad, *rgb = buf + 5 * S_pad;
  int32_t* evaluated = reinterpret_cast<int32_t*>(buf + 4 * S_pad);      // all-ones bits where evaluated
  std::fill(h, h + S_pad, 0.0f);
  std::fill(evaluated, evaluated + S_pad, 0);
  for (int64_t j = first; j < stop; ++j) {
    const int64_t s = c.fp[j] - r * S;
    h[s] = std::min(c.hs[j], c.clamp);
    evaluated[s] = -1;
  }
  const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f);
  for (int64_t s = 0; s < S_pad; s += 8) {
    const __m256 ev = _mm256_castsi256_ps(_mm256_loadu_si256(reinterpret_cast<const __m256i*>(evaluated + s)));
    const __m256 sigma = _mm256_and_ps(ev, exp8(_mm256_loadu_ps(h + s)));
    const __m256 t = _mm256_mul_ps(sigma, _mm256_maskload_ps(c.delta + r * S + s, first_lanes8(S - s)));
    _mm256_storeu_ps(tau + s, t);
    _mm256_storeu_ps(alpha + s, _mm256_sub_ps(one, exp8(_mm256_sub_ps(zero, t))));
  }
  transmittance_exponents(tau, w, S);
  for (int64_t s = 0; s < S; s += 8) {
    const __m256 lanes = _mm256_castsi256_ps(first_lanes8(S - s));
    _mm256_storeu_ps(w + s, _mm256_and_ps(lanes, _mm256_mul_ps(exp8(_mm256_loadu_ps(w + s)), _mm256_loadu_ps(alpha + s))));
  }
  const int64_t n_color = 3 * (stop - first);
  for (int64_t k = 0; k < n_color; k += 8) {
    const __m256i lanes = first_lanes8(n_color - k);
    const __m256 x = _mm256_maskload_ps(c.hc + 3 * first + k, lanes);
    _mm256_maskstore_ps(rgb + k, lanes, _mm256_div_ps(one, _mm256_add_ps(one, exp8(_mm256_sub_ps(zero, x)))));
  }
  finish_ray(c, r, w, rgb);
}
#endif

std::vector<at::Tensor> composite_rays(at::Tensor h_sigma, at::Tensor h_color, at::Tensor flat,
                                       at::Tensor starts, at::Tensor delta, at::Tensor background,
                                       double max_h_sigma, bool vector_path) {
  for (const auto* x : {&h_sigma, &h_color, &delta, &background})
    TORCH_CHECK(x->scalar_type() == at::kFloat && x->device().is_cpu(), "composite_rays: float32 CPU tensors");
  TORCH_CHECK(delta.dim() == 2 && starts.dim() == 1 && starts.size(0) == delta.size(0) + 1 &&
                  background.dim() == 2 && background.size(0) == delta.size(0) && background.size(1) == 3 &&
                  h_color.dim() == 2 && h_color.size(1) == 3 && h_color.size(0) == h_sigma.size(0) &&
                  flat.size(0) == h_sigma.size(0) && starts.scalar_type() == at::kLong &&
                  flat.scalar_type() == at::kLong,
              "composite_rays: h_sigma (M,), h_color (M, 3), flat (M,), starts (R + 1,), delta (R, S), background (R, 3)");
  const int64_t n_rays = delta.size(0), S = delta.size(1);
  auto color = delta.new_empty({n_rays, 3});
  auto opacity = delta.new_empty({n_rays});
  h_sigma = h_sigma.contiguous();
  h_color = h_color.contiguous();
  delta = delta.contiguous();
  background = background.contiguous();
  flat = flat.contiguous();
  starts = starts.contiguous();
  const RayComposite c{h_sigma.data_ptr<float>(), h_color.data_ptr<float>(), delta.data_ptr<float>(),
                       background.data_ptr<float>(), flat.data_ptr<int64_t>(), starts.data_ptr<int64_t>(), S,
                       static_cast<float>(max_h_sigma), color.data_ptr<float>(), opacity.data_ptr<float>()};
  const bool avx512 = vector_path && avx512_available() && S <= 64 * kLanes;
#ifdef DUALNERF_HAVE_AVX2
  const bool avx2 = vector_path && !avx512;
#endif
  parallel_for(0, n_rays, 256, [&](int64_t begin, int64_t end) {
    std::vector<float> buf(vector_path ? 8 * ((S + kLanes - 1) / kLanes * kLanes) : 0);
    for (int64_t r = begin; r < end; ++r) {
#ifdef DUALNERF_HAVE_AVX512
      if (avx512) {
        composite_ray_avx512(c, r, buf.data());
        continue;
      }
#endif
#ifdef DUALNERF_HAVE_AVX2
      if (avx2) {
        composite_ray_avx2(c, r, buf.data());
        continue;
      }
#endif
      composite_ray_scalar(c, r);
    }
  });
  return {color, opacity};
}
