// Shared declarations of the field kernels (dualnerf.kernels), one extension built from the files beside
// this one: lookups.cpp (feature-table look-ups and their backward), inference.cpp (look-ups + MLPs of a
// field without autograd, bf16/AMX; the layer code in mlp.h), mlp_train.cpp (the MLPs' training forward
// and backward), adam.cpp (the trainer's Adam), sampler.cpp (the render sampler),
// composite.cpp (a render's packing and compositing) and module.cpp (the Python bindings).
//
// Build flags (dualnerf/kernels/__init__.py): -O3 -ffp-contract=off, so no multiply-add is fused unless
// the code asks for it; that is what keeps each kernel bit-for-bit equal to the torch code it states.
#pragma once

// at::Tensor and its methods only (outputs come from x.new_empty): ~4 s of parsing per file on a slow
// core instead of ~15 s for <torch/types.h> or ~9 s with the per-operator factory headers; module.cpp adds
// the Python bindings.
#include <ATen/core/Tensor.h>

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <exception>
#include <mutex>
#include <optional>
#include <vector>

#if defined(__x86_64__) || defined(__i386__)
#include <xmmintrin.h>   // _mm_getcsr / _mm_setcsr (SSE: every x86-64 CPU)
#endif

// DUALNERF_NO_AVX512 (DUALNERF_KERNEL_BUILD=portable): a build with the portable code only, as on a
// compiler or CPU without AVX-512; it must give the same bits (tests/test_kernel_threads.py). Where the
// building CPU has AVX2 and FMA, the whole extension is compiled with -mavx2 -mfma (__init__.py isa_flags)
// and the MLP layers' portable code runs as AVX2 tiles (mlp.h, mlp_train.cpp), the same chains again
// (tests/test_kernel_build.py compares it with the generic build).
#if defined(__x86_64__) && defined(__GNUC__) && !defined(DUALNERF_NO_AVX512)
#include <cpuid.h>
#include <immintrin.h>
#include <sys/syscall.h>
#include <unistd.h>
#define DUALNERF_HAVE_AVX512 1   // compiled in with a target attribute; used where the CPU has it
#endif

// Builds with -mavx2 -mfma (__init__.py isa_flags, where the building CPU has both): AVX2 code for the MLP
// layers (mlp.h, mlp_train.cpp) and the look-ups (lookups.cpp), used where the CPU has no AVX-512.
#if defined(__x86_64__) && defined(__GNUC__) && defined(__AVX2__) && defined(__FMA__)
#include <immintrin.h>
#define DUALNERF_HAVE_AVX2 1
#endif

// Before the loops over a register tile's rows and vectors: unrolled completely before GCC decides where
// the accumulator array lives, so it stays in registers. Without it GCC 12 moved the accumulators through
// the stack on every step of the AVX2 tiles (~1.5x their time) and of the AVX-512 weight-gradient tiles
// with masked loads (benchmarks/profile_registers.py lists such loops).
#define DUALNERF_UNROLL _Pragma("GCC unroll 16")

namespace dualnerf {

#ifdef DUALNERF_HAVE_AVX512
inline bool avx512_available() { return __builtin_cpu_supports("avx512f"); }
#else
inline bool avx512_available() { return false; }
#endif

// ---- Threads ----
//
// The kernels run on their own OpenMP threads (set_threads, module.cpp), not torch's intra-op pool:
// the pipeline keeps torch on one thread, because torch's element-wise kernels compute a chunk's tail
// with scalar code that rounds differently from the vector code, so their bits depend on how many
// threads split a tensor. Every kernel here is written so that an output element does not depend on
// which thread or chunk computed it (no cross-element sums in a partition-dependent order), so the
// kernels may use any number of threads and still give the same bits.
int kernel_threads();

// ---- Denormals ----
//
// Every kernel computes with subnormal floats flushed to zero: its inputs read as zero (DAZ) and a result
// that would be subnormal is stored as zero (FTZ). A training step's gradients reach subnormal values
// (transmittance behind a surface times small output gradients, their squares in Adam), and each
// subnormal operand or result of a vector instruction costs a microcode assist: the MLP backward took
// 12 ms instead of 7.6 ms on a real editing batch. The mode is set at each kernel's entry (module.cpp)
// and on each of its threads (parallel_for), and the caller's mode is restored on return, so the bits
// do not depend on the thread count or on what the calling Python thread had set.
#if defined(__x86_64__) || defined(__i386__)
class FlushDenormals {
 public:
  FlushDenormals() : saved_(_mm_getcsr()) { _mm_setcsr(saved_ | kFlushToZero | kDenormalsAreZero); }
  ~FlushDenormals() { _mm_setcsr(saved_); }
  FlushDenormals(const FlushDenormals&) = delete;
  FlushDenormals& operator=(const FlushDenormals&) = delete;

 private:
  static constexpr unsigned kFlushToZero = 0x8000, kDenormalsAreZero = 0x0040;   // MXCSR bits 15 and 6
  unsigned saved_;
};
#else
class FlushDenormals {};   // other CPUs keep their default (they have their own key: the CPU enters it)
#endif

// f(chunk_begin, chunk_end) over [begin, end) in at most kernel_threads() contiguous chunks whose sizes
// are multiples of `grain` (but the last); the first exception thrown in a chunk is rethrown here.
template <typename F>
void parallel_for(int64_t begin, int64_t end, int64_t grain, F&& f) {
  const int64_t n = end - begin;
  if (n <= 0) return;
  grain = std::max<int64_t>(grain, 1);
  const int64_t grains = (n + grain - 1) / grain;
  const int64_t chunks = std::min<int64_t>(kernel_threads(), grains);
  if (chunks <= 1 || omp_in_parallel()) {
    f(begin, end);
    return;
  }
  const int64_t size = (grains + chunks - 1) / chunks * grain;
  std::exception_ptr error;
  std::mutex error_lock;
#pragma omp parallel num_threads(static_cast<int>(chunks))
  {
    FlushDenormals flushed;   // OpenMP's threads keep their own floating-point mode
    const int64_t b = begin + omp_get_thread_num() * size, e = std::min(end, b + size);
    if (b < e) {
      try {
        f(b, e);
      } catch (...) {
        std::lock_guard<std::mutex> hold(error_lock);
        if (!error) error = std::current_exception();
      }
    }
  }
  if (error) std::rethrow_exception(error);
}

struct Axis {
  int64_t i0;   // lower corner index
  float f;      // weight of the upper corner
};

inline Axis axis_coord(float c, int64_t size) {
  float p = (c + 1.0f) * 0.5f * static_cast<float>(size - 1);
  p = std::min(p > 0.0f ? p : 0.0f, static_cast<float>(size - 1));   // NaN -> 0: never an out-of-range read
  // p >= 0 here, so truncation is floor (and much cheaper: std::floor is a library call without SSE4.1).
  int64_t i0 = std::min(static_cast<int64_t>(p), size - 2);
  return {i0, p - static_cast<float>(i0)};
}

// Table t: kind 3 = dense grid (D, H, W, C) read by (x, y, z) -> (w, h, d); kind 2 = plane (H, W, C)
// read by (x[a0], x[a1]) -> (w, h).
struct Table {
  int kind;
  int64_t res;
  int64_t channels;
  int64_t stride;   // floats from one cell to the next: channels, or 4 in an interleaved pair table
  int a0, a1;
  int64_t column;
};

inline std::vector<Table> describe(const std::vector<at::Tensor>& dense, const std::vector<at::Tensor>& planes) {
  static const int axes[3][2] = {{0, 1}, {0, 2}, {1, 2}};
  std::vector<Table> tables;
  int64_t column = 0;
  for (const auto& g : dense) {
    TORCH_CHECK(g.dim() == 5 && g.size(0) == 1 && g.size(2) == g.size(3) && g.size(3) == g.size(4),
                "dense grid must be (1, C, R, R, R)");
    tables.push_back({3, g.size(2), g.size(1), g.size(1), 0, 0, column});
    column += g.size(1);
  }
  for (size_t i = 0; i < planes.size(); ++i) {
    const auto& p = planes[i];
    TORCH_CHECK(p.dim() == 4 && p.size(0) == 1 && p.size(2) == p.size(3), "plane must be (1, C, R, R)");
    tables.push_back({2, p.size(2), p.size(1), p.size(1), axes[i % 3][0], axes[i % 3][1], column});
    column += p.size(1);
  }
  return tables;
}

inline std::vector<at::Tensor> channels_last(const std::vector<at::Tensor>& tensors, bool dense) {
  std::vector<at::Tensor> out;
  for (const auto& t : tensors) {
    TORCH_CHECK(t.scalar_type() == at::kFloat && t.device().is_cpu(), "tables must be float32 CPU tensors");
    out.push_back(t.contiguous(dense ? at::MemoryFormat::ChannelsLast3d : at::MemoryFormat::ChannelsLast));
  }
  return out;
}

inline int64_t table_cells(const Table& t) { return t.kind == 3 ? t.res * t.res * t.res : t.res * t.res; }

inline int64_t total_columns(const std::vector<Table>& tables) {
  return tables.empty() ? 0 : tables.back().column + tables.back().channels;
}

// Channels-last copies of the tables (no copy when they are stored so) appended to `keep`, which holds
// them alive while the kernel reads their data pointers.
inline std::vector<const float*> table_data(const std::vector<at::Tensor>& dense, const std::vector<at::Tensor>& planes,
                                     std::vector<at::Tensor>& keep) {
  std::vector<const float*> data;
  for (auto& g : channels_last(dense, true)) { keep.push_back(g); data.push_back(g.data_ptr<float>()); }
  for (auto& p : channels_last(planes, false)) { keep.push_back(p); data.push_back(p.data_ptr<float>()); }
  return data;
}

// Blocks of points in parallel, each handed to block(begin, end): a block's look-ups into one table hit
// nearby cells (neighbouring samples along a ray), which stay in cache while the block runs table by table.
template <typename Block>
void for_each_block(int64_t m, Block&& block) {
  constexpr int64_t kBlock = 1024;
  parallel_for(0, (m + kBlock - 1) / kBlock, 1, [&](int64_t block_begin, int64_t block_end) {
    for (int64_t b = block_begin; b < block_end; ++b) block(b * kBlock, std::min(m, (b + 1) * kBlock));
  });
}

// Calls visit(offset_in_table, weight) for the corners of point `x` in table `t`.
template <typename Visit>
inline void corners(const Table& t, const float* x, Visit&& visit) {
  const int64_t r = t.res, c = t.stride;
  if (t.kind == 3) {
    Axis ax = axis_coord(x[0], r), ay = axis_coord(x[1], r), az = axis_coord(x[2], r);
    const int64_t base = ((az.i0 * r + ay.i0) * r + ax.i0) * c;
    const int64_t sx = c, sy = r * c, sz = r * r * c;
    const float wx[2] = {1.0f - ax.f, ax.f}, wy[2] = {1.0f - ay.f, ay.f}, wz[2] = {1.0f - az.f, az.f};
    for (int dz = 0; dz < 2; ++dz)
      for (int dy = 0; dy < 2; ++dy) {
        const float wzy = wz[dz] * wy[dy];
        const int64_t row = base + dz * sz + dy * sy;
        visit(row, wzy * wx[0]);
        visit(row + sx, wzy * wx[1]);
      }
  } else {
    Axis au = axis_coord(x[t.a0], r), av = axis_coord(x[t.a1], r);
    const int64_t base = (av.i0 * r + au.i0) * c;
    const int64_t su = c, sv = r * c;
    visit(base, (1.0f - av.f) * (1.0f - au.f));
    visit(base + su, (1.0f - av.f) * au.f);
    visit(base + sv, av.f * (1.0f - au.f));
    visit(base + sv + su, av.f * au.f);
  }
}

// Chunks of gradient values that encode_backward_into flags as touched (for adam_step_touched). Chunks
// never straddle a corner's features (1, 2, 4 or 8 values at an offset that is a multiple of their count).
constexpr int64_t kTouchChunk = 16;

constexpr int kLanes = 16;   // floats per AVX-512 vector; MLP layer widths are padded to a multiple of this

#ifdef DUALNERF_HAVE_AVX512
// The first `left` lanes of a 16-lane vector (all from 16 on, none for left <= 0): masked row tails.
inline __mmask16 first_lanes(int64_t left) {
  return left >= kLanes ? static_cast<__mmask16>(0xFFFF)
                        : static_cast<__mmask16>((1u << (left > 0 ? left : 0)) - 1u);
}

// exp of 16 floats: exp(x) = 2^n exp(r) with n = round(x / ln 2) and r = x - n ln 2 (ln 2 in two parts, so r
// is exact to float rounding, |r| <= ln 2 / 2), exp(r) by its Taylor polynomial to degree 7 (truncation
// < 1e-8 relative): within a few ulp of std::exp. Inputs below -87 give ~1e-38 instead of a denormal or 0.
__attribute__((target("avx512f"))) inline __m512 exp16(__m512 x) {
  x = _mm512_min_ps(_mm512_max_ps(x, _mm512_set1_ps(-87.0f)), _mm512_set1_ps(88.0f));
  const __m512 n = _mm512_roundscale_ps(_mm512_mul_ps(x, _mm512_set1_ps(1.44269504088896341f)),
                                        _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  __m512 r = _mm512_fnmadd_ps(n, _mm512_set1_ps(0.693145751953125f), x);      // ln 2's leading bits
  r = _mm512_fnmadd_ps(n, _mm512_set1_ps(1.428606765330187e-06f), r);        // and the rest
  __m512 p = _mm512_set1_ps(1.0f / 5040.0f);
  for (const float k : {1.0f / 720.0f, 1.0f / 120.0f, 1.0f / 24.0f, 1.0f / 6.0f, 0.5f, 1.0f, 1.0f})
    p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(k));
  return _mm512_scalef_ps(p, n);
}
#endif

// exp16 for one float, in the same operations (fused multiply-adds included), hence the same bits: a
// kernel's portable path and a vector path's row tails use it where the vector code uses exp16.
inline float exp_scalar(float x) {
  x = std::min(std::max(x, -87.0f), 88.0f);
  const float n = std::nearbyint(x * 1.44269504088896341f);
  float r = std::fma(-n, 0.693145751953125f, x);
  r = std::fma(-n, 1.428606765330187e-06f, r);
  float p = 1.0f / 5040.0f;
  for (const float k : {1.0f / 720.0f, 1.0f / 120.0f, 1.0f / 24.0f, 1.0f / 6.0f, 0.5f, 1.0f, 1.0f}) p = std::fma(p, r, k);
  // p * 2^n, as std::ldexp (a libm call that took ~3% of a CPU without AVX-512's test suite): n is in
  // [-126, 127] and p in [1.4, 1.42) at n = -126, so the product is a normal float and exact.
  const int32_t bits = (static_cast<int32_t>(n) + 127) << 23;
  float scale;
  std::memcpy(&scale, &bits, sizeof scale);
  return p * scale;
}

#ifdef DUALNERF_HAVE_AVX2
// exp16's operations on 8 floats (builds with the AVX2 flags), with 2^n built as exp_scalar builds it: the
// same bits as both.
inline __m256 exp8(__m256 x) {
  x = _mm256_min_ps(_mm256_max_ps(x, _mm256_set1_ps(-87.0f)), _mm256_set1_ps(88.0f));
  const __m256 n = _mm256_round_ps(_mm256_mul_ps(x, _mm256_set1_ps(1.44269504088896341f)),
                                   _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  __m256 r = _mm256_fnmadd_ps(n, _mm256_set1_ps(0.693145751953125f), x);
  r = _mm256_fnmadd_ps(n, _mm256_set1_ps(1.428606765330187e-06f), r);
  __m256 p = _mm256_set1_ps(1.0f / 5040.0f);
  for (const float k : {1.0f / 720.0f, 1.0f / 120.0f, 1.0f / 24.0f, 1.0f / 6.0f, 0.5f, 1.0f, 1.0f})
    p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(k));
  const __m256i bits = _mm256_slli_epi32(_mm256_add_epi32(_mm256_cvtps_epi32(n), _mm256_set1_epi32(127)), 23);
  return _mm256_mul_ps(p, _mm256_castsi256_ps(bits));
}

// The first `left` lanes of an 8-lane vector as all-ones (none for left <= 0): masked loads of row tails.
inline __m256i first_lanes8(int64_t left) {
  const int count = static_cast<int>(std::min<int64_t>(std::max<int64_t>(left, 0), 8));
  return _mm256_cmpgt_epi32(_mm256_set1_epi32(count), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
}
#endif

// Every table's features for points [begin, end) into rows (i - row0) of out_a (and out_b: the second
// field's tables data_b, when given); lookups.cpp.
void lookup_range(const std::vector<Table>& tables, const std::vector<const float*>& data_a,
                  const std::vector<const float*>* data_b, const float* xp, float* out_a, float* out_b,
                  int64_t n_out, int64_t begin, int64_t end, int64_t row0, bool vector_path);

}  // namespace dualnerf

// The functions module.cpp binds, each defined and documented in the file named above it.

// lookups.cpp
at::Tensor encode_forward(at::Tensor x, std::vector<at::Tensor> dense, std::vector<at::Tensor> planes,
                          bool vector_path);
std::vector<at::Tensor> encode_forward_pair(at::Tensor x, std::vector<at::Tensor> dense_a,
                                            std::vector<at::Tensor> planes_a, std::vector<at::Tensor> dense_b,
                                            std::vector<at::Tensor> planes_b, bool vector_path);
std::vector<at::Tensor> encode_backward(at::Tensor x, at::Tensor grad_out, std::vector<at::Tensor> dense,
                                        std::vector<at::Tensor> planes, bool vector_path);
void encode_backward_into(at::Tensor x, at::Tensor grad_out, std::vector<at::Tensor> dense,
                          std::vector<at::Tensor> planes, std::vector<at::Tensor> grads,
                          std::vector<at::Tensor> touched, bool vector_path);
void zero_touched(at::Tensor grad, at::Tensor touched);

// inference.cpp
std::vector<at::Tensor> field_inference(at::Tensor x, at::Tensor sh, std::vector<at::Tensor> dense_a,
                                        std::vector<at::Tensor> planes_a, std::vector<at::Tensor> mlp_a,
                                        std::vector<at::Tensor> dense_b, std::vector<at::Tensor> planes_b,
                                        std::vector<at::Tensor> mlp_b, double w_density, double w_color,
                                        std::vector<at::Tensor> interleaved, std::optional<at::Tensor> sh_index,
                                        bool vector_path, bool bf16, bool amx, bool density_only);
void interleave_pair_into(std::vector<at::Tensor> out, std::vector<at::Tensor> dense_a,
                          std::vector<at::Tensor> planes_a, std::vector<at::Tensor> dense_b,
                          std::vector<at::Tensor> planes_b, bool write_first);
std::vector<at::Tensor> interleave_pair(std::vector<at::Tensor> dense_a, std::vector<at::Tensor> planes_a,
                                        std::vector<at::Tensor> dense_b, std::vector<at::Tensor> planes_b);
std::vector<at::Tensor> mlp_inference(at::Tensor features, at::Tensor sh, std::vector<at::Tensor> mlp,
                                      bool vector_path);
bool vector_path_available();
bool amx_path_available();

// mlp_train.cpp
std::vector<at::Tensor> mlp_train_forward(at::Tensor features, at::Tensor sh,
                                          std::optional<at::Tensor> sh_index, std::vector<at::Tensor> mlp,
                                          bool vector_path);
std::vector<at::Tensor> mlp_train_backward(at::Tensor grad_sigma, at::Tensor grad_color,
                                           at::Tensor features, at::Tensor hidden_density,
                                           at::Tensor color_in, at::Tensor hidden_color,
                                           std::vector<at::Tensor> mlp, std::vector<at::Tensor> weights,
                                           int64_t n_sh, bool vector_path);

// adam.cpp
void adam_step(at::Tensor param, at::Tensor grad, at::Tensor exp_avg, at::Tensor exp_avg_sq, double beta1,
               double beta2, double step_size, double bias_correction2_sqrt, double eps, bool skip_zero);
void adam_step_touched(at::Tensor param, at::Tensor grad, at::Tensor touched, at::Tensor exp_avg,
                       at::Tensor exp_avg_sq, double beta1, double beta2, double step_size,
                       double bias_correction2_sqrt, double eps);

// sampler.cpp
std::vector<at::Tensor> ray_samples(at::Tensor origins, at::Tensor dirs, at::Tensor t_start,
                                    at::Tensor t_end, at::Tensor density, at::Tensor mask, double scale,
                                    int64_t n_proposal, int64_t n_samples, double uniform_share,
                                    at::Tensor jitter, bool vector_path);

// composite.cpp
std::vector<at::Tensor> occupied_samples(at::Tensor origins, at::Tensor dirs, at::Tensor t,
                                         at::Tensor mask);
std::vector<at::Tensor> composite_rays(at::Tensor h_sigma, at::Tensor h_color, at::Tensor flat,
                                       at::Tensor starts, at::Tensor delta, at::Tensor background,
                                       double max_h_sigma, bool vector_path);
