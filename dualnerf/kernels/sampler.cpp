#include "kernels.h"

using namespace dualnerf;

// ---- The render sampler (dualnerf.rendering.ray_samples): proposal intervals + occupancy test per ray ----
//
// Per ray, in cache: the proposal (the occupancy grid's scaled density at n_proposal bin centres,
// composited), its pdf mixed with the uniform share, inverse-transform sampling of the interval edges at
// the quantiles (i - 0.5 + jitter_i) / S (a merge walk: the quantiles are increasing), and the
// occupancy mask at the interval midpoints. On AVX-512 the proposal runs for 16 rays at once, one per
// lane (its exp and sequential sums were 70% of a render's sampler). The same formulas as proposal_intervals and
// OccupancyGrid.occupied in torch, which stay the reference; they agree to float32 rounding (exp and
// the sums round differently), and the cells of given points are bit-for-bit the reference's. The
// AVX-512 and portable paths give the same bits, so a ray's samples do not depend on its chunk.
inline int64_t grid_cell(const float* o, const float* d, float t, float half_r, float top, int64_t r) {
  int64_t cell[3];
  for (int a = 0; a < 3; ++a) {
    const float x = o[a] + t * d[a];
    const float c = (x + 1.0f) * half_r;
    cell[a] = static_cast<int64_t>(std::min(c > 0.0f ? c : 0.0f, top));
  }
  return (cell[0] * r + cell[1]) * r + cell[2];
}

struct SamplerInputs {
  const float *op, *dp, *sp, *ep, *grid, *jp;
  const bool* mp;
  int64_t r, P, S;
  float half_r, top, fscale, keep, uniform_bin;
  float *tp, *deltap;
  bool* occp;
};

// Ray i's proposal: pdf[k * stride] (normalised, with the uniform share) and cdf[k * stride], k <= P.
void proposal_scalar(const SamplerInputs& in, int64_t i, float* pdf, float* cdf, int64_t stride) {
  const float* o = in.op + 3 * i;
  const float* d = in.dp + 3 * i;
  const float start = in.sp[i], stop = in.ep[i];
  const float length = stop - start > 0.0f ? stop - start : 0.0f;
  const float step = length / static_cast<float>(in.P);
  // Proposal weights w_k = T_k (1 - exp(-tau_k)) of the grid density at the bin centres, with the
  // transmittance carried along (T_k+1 = T_k exp(-tau_k)): one exp per bin that holds density.
  float transmittance = 1.0f, weight_sum = 0.0f;
  for (int64_t k = 0; k < in.P; ++k) {
    const float tc = start + (static_cast<float>(k) + 0.5f) * step;
    const float tau = in.fscale * in.grid[grid_cell(o, d, tc, in.half_r, in.top, in.r)] * step;
    float w = 0.0f;
    if (tau > 0.0f) {
      const float survive = exp_scalar(-tau);
      w = transmittance * (1.0f - survive);
      transmittance *= survive;
    }
    pdf[k * stride] = w;
    weight_sum += w;
  }
  float pdf_sum = 0.0f;
  for (int64_t k = 0; k < in.P; ++k) {
    pdf[k * stride] = in.keep * pdf[k * stride] / (weight_sum + 1e-6f) + in.uniform_bin;
    pdf_sum += pdf[k * stride];
  }
  cdf[0] = 0.0f;
  for (int64_t k = 0; k < in.P; ++k) {
    pdf[k * stride] = pdf[k * stride] / pdf_sum;
    cdf[(k + 1) * stride] = cdf[k * stride] + pdf[k * stride];
  }
  cdf[in.P * stride] = 1.0f;
}

#ifdef DUALNERF_HAVE_AVX512
// proposal_scalar for the 16 rays i0 .. i0 + 15, one per lane (pdf, cdf with stride 16), in the same
// float operations (exp16 is exp_scalar's vector form), hence the same bits.
__attribute__((target("avx512f"))) void proposal_avx512(const SamplerInputs& in, int64_t i0, float* pdf, float* cdf) {
  const __m512i lane = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
  const __m512i three = _mm512_mullo_epi32(lane, _mm512_set1_epi32(3));
  __m512 o[3], d[3];
  for (int a = 0; a < 3; ++a) {
    o[a] = _mm512_i32gather_ps(_mm512_add_epi32(three, _mm512_set1_epi32(a)), in.op + 3 * i0, 4);
    d[a] = _mm512_i32gather_ps(_mm512_add_epi32(three, _mm512_set1_epi32(a)), in.dp + 3 * i0, 4);
  }
  const __m512 zero = _mm512_setzero_ps(), one = _mm512_set1_ps(1.0f);
  const __m512 start = _mm512_loadu_ps(in.sp + i0), stop = _mm512_loadu_ps(in.ep + i0);
  const __m512 diff = _mm512_sub_ps(stop, start);
  const __m512 length = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(diff, zero, _CMP_GT_OQ), zero, diff);
  const __m512 step = _mm512_div_ps(length, _mm512_set1_ps(static_cast<float>(in.P)));
  const __m512 half_r = _mm512_set1_ps(in.half_r), top = _mm512_set1_ps(in.top);
  const __m512i r = _mm512_set1_epi32(static_cast<int>(in.r));
  __m512 transmittance = one, weight_sum = zero;
  for (int64_t k = 0; k < in.P; ++k) {
    const __m512 tc = _mm512_add_ps(start, _mm512_mul_ps(_mm512_set1_ps(static_cast<float>(k) + 0.5f), step));
    __m512i cell[3];
    for (int a = 0; a < 3; ++a) {
      const __m512 c = _mm512_mul_ps(_mm512_add_ps(_mm512_add_ps(o[a], _mm512_mul_ps(tc, d[a])), one), half_r);
      cell[a] = _mm512_cvttps_epi32(_mm512_min_ps(_mm512_max_ps(c, zero), top));   // NaN -> 0, as grid_cell
    }
    const __m512i index = _mm512_add_epi32(
        _mm512_mullo_epi32(_mm512_add_epi32(_mm512_mullo_epi32(cell[0], r), cell[1]), r), cell[2]);
    const __m512 tau = _mm512_mul_ps(_mm512_mul_ps(_mm512_set1_ps(in.fscale), _mm512_i32gather_ps(index, in.grid, 4)),
                                     step);
    const __mmask16 dense = _mm512_cmp_ps_mask(tau, zero, _CMP_GT_OQ);
    const __m512 survive = exp16(_mm512_sub_ps(zero, tau));
    const __m512 w = _mm512_maskz_mul_ps(dense, transmittance, _mm512_sub_ps(one, survive));
    transmittance = _mm512_mask_mul_ps(transmittance, dense, transmittance, survive);
    _mm512_storeu_ps(pdf + 16 * k, w);
    weight_sum = _mm512_add_ps(weight_sum, w);
  }
  const __m512 keep = _mm512_set1_ps(in.keep), uniform_bin = _mm512_set1_ps(in.uniform_bin);
  const __m512 denominator = _mm512_add_ps(weight_sum, _mm512_set1_ps(1e-6f));
  __m512 pdf_sum = zero;
  for (int64_t k = 0; k < in.P; ++k) {
    const __m512 p = _mm512_add_ps(_mm512_div_ps(_mm512_mul_ps(keep, _mm512_loadu_ps(pdf + 16 * k)), denominator),
                                   uniform_bin);
    _mm512_storeu_ps(pdf + 16 * k, p);
    pdf_sum = _mm512_add_ps(pdf_sum, p);
  }
  __m512 cumulative = zero;
  _mm512_storeu_ps(cdf, zero);
  for (int64_t k = 0; k < in.P; ++k) {
    const __m512 p = _mm512_div_ps(_mm512_loadu_ps(pdf + 16 * k), pdf_sum);
    _mm512_storeu_ps(pdf + 16 * k, p);
    cumulative = _mm512_add_ps(cumulative, p);
    _mm512_storeu_ps(cdf + 16 * (k + 1), cumulative);
  }
  _mm512_storeu_ps(cdf + 16 * in.P, one);
}

// place_samples for the 16 rays i0 .. i0 + 15, one per lane, from proposal_avx512's pdf and cdf (row k:
// the 16 rays' entry k); edges: scratch of 16 (S + 1) floats. The scalar merge walk turned around: the
// bins k go by in the outer loop (an aligned load per cdf row instead of a gather per step), and at bin k
// each lane places its next edges while !(cdf[k + 1] <= u), which is where the scalar walk stops
// advancing and places edge j in bin k. Then the intervals of all 16 rays, sample by sample. The same
// comparisons in the same sequence per lane and the same float operations per edge and sample: the same
// bits. (The scalar walk's branches, a division per edge and the cell tests were ~6% of a render.)
__attribute__((target("avx512f"))) void place_samples_avx512(const SamplerInputs& in, int64_t i0, const float* pdf,
                                                             const float* cdf, float* edges) {
  const __m512i lane = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
  const int64_t S = in.S, P = in.P;
  const __m512 zero = _mm512_setzero_ps(), one = _mm512_set1_ps(1.0f), half = _mm512_set1_ps(0.5f);
  const __m512 start = _mm512_loadu_ps(in.sp + i0), stop = _mm512_loadu_ps(in.ep + i0);
  const __m512 diff = _mm512_sub_ps(stop, start);
  const __m512 length = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(diff, zero, _CMP_GT_OQ), zero, diff);
  const __m512 step = _mm512_div_ps(length, _mm512_set1_ps(static_cast<float>(P)));
  const __mmask16 valid = _mm512_cmp_ps_mask(stop, start, _CMP_GT_OQ);
  const __m512i one_i = _mm512_set1_epi32(1), sixteen = _mm512_set1_epi32(16);
  const __m512i last_edge = _mm512_set1_epi32(static_cast<int>(S));
  const __m512i row_jitter = _mm512_mullo_epi32(lane, _mm512_set1_epi32(static_cast<int>(S - 1)));
  const __m512 samples = _mm512_set1_ps(static_cast<float>(S));
  _mm512_storeu_ps(edges, start);                                                  // edges[0]
  _mm512_storeu_ps(edges + 16 * S, _mm512_mask_blend_ps(valid, start, stop));       // stop > start ? stop : start
  // Per lane: j, the next edge to place (1 .. S - 1; S: done), and its quantile u_j = (j - 0.5 + offset) / S
  // with offset = jitter[ray][j - 1], or 0.5.
  __m512i j = one_i;
  __m512 u = zero;
  auto next_quantile = [&](__mmask16 lanes) __attribute__((target("avx512f"))) {
    const __m512 offset = in.jp ? _mm512_mask_i32gather_ps(half, lanes, _mm512_add_epi32(row_jitter, _mm512_sub_epi32(j, one_i)),
                                                           in.jp + i0 * (S - 1), 4)
                                : half;
    u = _mm512_mask_div_ps(u, lanes, _mm512_add_ps(_mm512_sub_ps(_mm512_cvtepi32_ps(j), half), offset), samples);
  };
  __mmask16 pending = _mm512_cmplt_epi32_mask(j, last_edge);
  next_quantile(pending);
  for (int64_t k = 0; k < P && pending; ++k) {
    const __m512 bin_cdf = _mm512_loadu_ps(cdf + 16 * k), bin_pdf = _mm512_loadu_ps(pdf + 16 * k);
    const __m512 bin = _mm512_set1_ps(static_cast<float>(k));
    const bool last_bin = k + 1 == P;      // the walk cannot advance past P - 1: it takes every remaining edge
    const __m512 next_cdf = last_bin ? zero : _mm512_loadu_ps(cdf + 16 * (k + 1));
    for (;;) {
      const __mmask16 here = last_bin ? pending : _mm512_mask_cmp_ps_mask(pending, next_cdf, u, _CMP_NLE_UQ);
      if (!here) break;
      __m512 frac = _mm512_div_ps(_mm512_sub_ps(u, bin_cdf), bin_pdf);
      frac = _mm512_min_ps(one, _mm512_max_ps(zero, frac));    // std::min(std::max(frac, 0), 1), NaN kept
      const __m512 edge = _mm512_add_ps(start, _mm512_mul_ps(_mm512_add_ps(bin, frac), step));
      _mm512_mask_i32scatter_ps(edges, here, _mm512_add_epi32(_mm512_mullo_epi32(j, sixteen), lane), edge, 4);
      j = _mm512_mask_add_epi32(j, here, j, one_i);
      pending = _mm512_mask_cmplt_epi32_mask(pending, j, last_edge);
      next_quantile(here & pending);
    }
  }
  // The intervals: midpoints, lengths and the occupancy of the midpoints, sample by sample.
  const __m512i three = _mm512_mullo_epi32(lane, _mm512_set1_epi32(3));
  __m512 o[3], d[3];
  for (int a = 0; a < 3; ++a) {
    o[a] = _mm512_i32gather_ps(_mm512_add_epi32(three, _mm512_set1_epi32(a)), in.op + 3 * i0, 4);
    d[a] = _mm512_i32gather_ps(_mm512_add_epi32(three, _mm512_set1_epi32(a)), in.dp + 3 * i0, 4);
  }
  const __m512 half_r = _mm512_set1_ps(in.half_r), top = _mm512_set1_ps(in.top);
  const __m512i r = _mm512_set1_epi32(static_cast<int>(in.r));
  const __m512i row_s = _mm512_mullo_epi32(lane, _mm512_set1_epi32(static_cast<int>(S)));
  alignas(64) int32_t cells[16];
  for (int64_t s = 0; s < S; ++s) {
    const __m512 e0 = _mm512_loadu_ps(edges + 16 * s), e1 = _mm512_loadu_ps(edges + 16 * (s + 1));
    const __m512 mid = _mm512_mul_ps(half, _mm512_add_ps(e1, e0));
    const __m512i out = _mm512_add_epi32(row_s, _mm512_set1_epi32(static_cast<int>(s)));
    _mm512_i32scatter_ps(in.tp + i0 * S, out, mid, 4);
    _mm512_i32scatter_ps(in.deltap + i0 * S, out, _mm512_sub_ps(e1, e0), 4);
    __m512i cell[3];
    for (int a = 0; a < 3; ++a) {
      const __m512 c = _mm512_mul_ps(_mm512_add_ps(_mm512_add_ps(o[a], _mm512_mul_ps(mid, d[a])), one), half_r);
      cell[a] = _mm512_cvttps_epi32(_mm512_min_ps(_mm512_max_ps(c, zero), top));   // NaN -> 0, as grid_cell
    }
    _mm512_store_si512(cells, _mm512_add_epi32(
        _mm512_mullo_epi32(_mm512_add_epi32(_mm512_mullo_epi32(cell[0], r), cell[1]), r), cell[2]));
    for (int l = 0; l < 16; ++l) in.occp[(i0 + l) * S + s] = ((valid >> l) & 1) && in.mp[cells[l]];
  }
}
#endif

#ifdef DUALNERF_HAVE_AVX2
// proposal_avx512's operations for the 8 rays i0 .. i0 + 7 (pdf, cdf with stride 8), for builds with the
// AVX2 flags on CPUs without AVX-512: the same bits. The edges are then placed by the scalar walk.
void proposal_avx2(const SamplerInputs& in, int64_t i0, float* pdf, float* cdf) {
  const __m256i three = _mm256_setr_epi32(0, 3, 6, 9, 12, 15, 18, 21);
  __m256 o[3], d[3];
  for (int a = 0; a < 3; ++a) {
    o[a] = _mm256_i32gather_ps(in.op + 3 * i0, _mm256_add_epi32(three, _mm256_set1_epi32(a)), 4);
    d[a] = _mm256_i32gather_ps(in.dp + 3 * i0, _mm256_add_epi32(three, _mm256_set1_epi32(a)), 4);
  }
  const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f);
  const __m256 start = _mm256_loadu_ps(in.sp + i0), stop = _mm256_loadu_ps(in.ep + i0);
  const __m256 diff = _mm256_sub_ps(stop, start);
  const __m256 length = _mm256_blendv_ps(zero, diff, _mm256_cmp_ps(diff, zero, _CMP_GT_OQ));
  const __m256 step = _mm256_div_ps(length, _mm256_set1_ps(static_cast<float>(in.P)));
  const __m256 half_r = _mm256_set1_ps(in.half_r), top = _mm256_set1_ps(in.top);
  const __m256i r = _mm256_set1_epi32(static_cast<int>(in.r));
  __m256 transmittance = one, weight_sum = zero;
  for (int64_t k = 0; k < in.P; ++k) {
    const __m256 tc = _mm256_add_ps(start, _mm256_mul_ps(_mm256_set1_ps(static_cast<float>(k) + 0.5f), step));
    __m256i cell[3];
    for (int a = 0; a < 3; ++a) {
      const __m256 c = _mm256_mul_ps(_mm256_add_ps(_mm256_add_ps(o[a], _mm256_mul_ps(tc, d[a])), one), half_r);
      cell[a] = _mm256_cvttps_epi32(_mm256_min_ps(_mm256_max_ps(c, zero), top));   // NaN -> 0, as grid_cell
    }
    const __m256i index = _mm256_add_epi32(
        _mm256_mullo_epi32(_mm256_add_epi32(_mm256_mullo_epi32(cell[0], r), cell[1]), r), cell[2]);
    const __m256 tau = _mm256_mul_ps(_mm256_mul_ps(_mm256_set1_ps(in.fscale), _mm256_i32gather_ps(in.grid, index, 4)),
                                     step);
    const __m256 dense = _mm256_cmp_ps(tau, zero, _CMP_GT_OQ);
    const __m256 survive = exp8(_mm256_sub_ps(zero, tau));
    const __m256 w = _mm256_and_ps(dense, _mm256_mul_ps(transmittance, _mm256_sub_ps(one, survive)));
    transmittance = _mm256_blendv_ps(transmittance, _mm256_mul_ps(transmittance, survive), dense);
    _mm256_storeu_ps(pdf + 8 * k, w);
    weight_sum = _mm256_add_ps(weight_sum, w);
  }
  const __m256 keep = _mm256_set1_ps(in.keep), uniform_bin = _mm256_set1_ps(in.uniform_bin);
  const __m256 denominator = _mm256_add_ps(weight_sum, _mm256_set1_ps(1e-6f));
  __m256 pdf_sum = zero;
  for (int64_t k = 0; k < in.P; ++k) {
    const __m256 p = _mm256_add_ps(_mm256_div_ps(_mm256_mul_ps(keep, _mm256_loadu_ps(pdf + 8 * k)), denominator),
                                   uniform_bin);
    _mm256_storeu_ps(pdf + 8 * k, p);
    pdf_sum = _mm256_add_ps(pdf_sum, p);
  }
  __m256 cumulative = zero;
  _mm256_storeu_ps(cdf, zero);
  for (int64_t k = 0; k < in.P; ++k) {
    const __m256 p = _mm256_div_ps(_mm256_loadu_ps(pdf + 8 * k), pdf_sum);
    _mm256_storeu_ps(pdf + 8 * k, p);
    cumulative = _mm256_add_ps(cumulative, p);
    _mm256_storeu_ps(cdf + 8 * (k + 1), cumulative);
  }
  _mm256_storeu_ps(cdf + 8 * in.P, one);
}
#endif

// Ray i's interval edges at the quantiles of its proposal (pdf, cdf with `stride`), written as midpoints,
// lengths and the occupancy of the midpoints. edges: scratch of S + 1 floats.
void place_samples(const SamplerInputs& in, int64_t i, const float* pdf, const float* cdf, int64_t stride,
                   float* edges) {
  const float* o = in.op + 3 * i;
  const float* d = in.dp + 3 * i;
  const float start = in.sp[i], stop = in.ep[i];
  const int64_t S = in.S, P = in.P;
  const float length = stop - start > 0.0f ? stop - start : 0.0f;
  const float step = length / static_cast<float>(P);
  // Edges at the quantiles u_0 = 0 < u_1 < ... < u_S = 1: bin = the last k with cdf[k] <= u.
  int64_t bin = 0;
  edges[0] = start;
  for (int64_t j = 1; j < S; ++j) {
    const float offset = in.jp ? in.jp[i * (S - 1) + (j - 1)] : 0.5f;
    const float u = (static_cast<float>(j) - 0.5f + offset) / static_cast<float>(S);
    while (bin + 1 < P && cdf[(bin + 1) * stride] <= u) ++bin;
    float frac = (u - cdf[bin * stride]) / pdf[bin * stride];
    frac = std::min(std::max(frac, 0.0f), 1.0f);
    edges[j] = start + (static_cast<float>(bin) + frac) * step;
  }
  edges[S] = stop > start ? stop : start;
  const bool valid = stop > start;
  for (int64_t j = 0; j < S; ++j) {
    const float mid = 0.5f * (edges[j + 1] + edges[j]);
    in.tp[i * S + j] = mid;
    in.deltap[i * S + j] = edges[j + 1] - edges[j];
    in.occp[i * S + j] = valid && in.mp[grid_cell(o, d, mid, in.half_r, in.top, in.r)];
  }
}

std::vector<at::Tensor> ray_samples(at::Tensor origins, at::Tensor dirs, at::Tensor t_start,
                                    at::Tensor t_end, at::Tensor density, at::Tensor mask, double scale,
                                    int64_t n_proposal, int64_t n_samples, double uniform_share,
                                    at::Tensor jitter, bool vector_path) {
  for (const auto* x : {&origins, &dirs, &t_start, &t_end, &density})
    TORCH_CHECK(x->scalar_type() == at::kFloat && x->device().is_cpu(), "ray_samples: float32 CPU tensors expected");
  TORCH_CHECK(mask.scalar_type() == at::kBool && mask.sizes() == density.sizes(), "ray_samples: bool mask like density");
  TORCH_CHECK(n_proposal >= 1 && n_samples >= 1, "ray_samples: at least one proposal bin and one sample");
  origins = origins.contiguous();
  dirs = dirs.contiguous();
  t_start = t_start.contiguous();
  t_end = t_end.contiguous();
  density = density.contiguous();
  mask = mask.contiguous();
  const int64_t n_rays = t_start.size(0), r = density.size(0), S = n_samples, P = n_proposal;
  const bool jittered = jitter.numel() > 0;
  if (jittered) {
    jitter = jitter.contiguous();
    TORCH_CHECK(jitter.scalar_type() == at::kFloat && jitter.size(0) == n_rays && jitter.size(1) == S - 1,
                "ray_samples: jitter must be (rays, samples - 1) float32");
  }
  auto t = t_start.new_empty({n_rays, S});
  auto delta = t_start.new_empty({n_rays, S});
  auto occupied = mask.new_empty({n_rays, S});
  const SamplerInputs in{origins.data_ptr<float>(), dirs.data_ptr<float>(), t_start.data_ptr<float>(),
                         t_end.data_ptr<float>(), density.data_ptr<float>(),
                         jittered ? jitter.data_ptr<float>() : nullptr, mask.data_ptr<bool>(), r, P, S,
                         0.5f * static_cast<float>(r), static_cast<float>(r - 1), static_cast<float>(scale),
                         static_cast<float>(1.0 - uniform_share),
                         static_cast<float>(uniform_share / static_cast<double>(P)), t.data_ptr<float>(),
                         delta.data_ptr<float>(), occupied.data_ptr<bool>()};
  // 16 rays at a time on AVX-512, 8 with AVX2 (one per lane; the grid's cells fit int32 there).
  const bool vec = vector_path && r * r * r < (int64_t(1) << 31);
  const bool avx512 = vec && avx512_available();
  parallel_for(0, n_rays, 16, [&](int64_t begin, int64_t end) {
    std::vector<float> pdf(16 * P), cdf(16 * (P + 1)), edges(16 * (S + 1));
    int64_t i = begin;
#ifdef DUALNERF_HAVE_AVX512
    if (avx512)
      for (; i + 16 <= end; i += 16) {
        proposal_avx512(in, i, pdf.data(), cdf.data());
        place_samples_avx512(in, i, pdf.data(), cdf.data(), edges.data());
      }
#endif
#ifdef DUALNERF_HAVE_AVX2
    if (vec && !avx512)
      for (; i + 8 <= end; i += 8) {
        proposal_avx2(in, i, pdf.data(), cdf.data());
        for (int lane = 0; lane < 8; ++lane)
          place_samples(in, i + lane, pdf.data() + lane, cdf.data() + lane, 8, edges.data());
      }
#endif
    for (; i < end; ++i) {
      proposal_scalar(in, i, pdf.data(), cdf.data(), 1);
      place_samples(in, i, pdf.data(), cdf.data(), 1, edges.data());
    }
  });
  return {t, delta, occupied};
}
