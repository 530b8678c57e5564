#include "mlp.h"

using namespace dualnerf;

// ---- Training: a field's MLPs forward (keeping what the backward needs) and backward ----
//
// The trainer's MLPs (RadianceField.heads under autograd) ran on torch's matmuls, whose weight gradients
// sum over the samples in an order that depends on the thread count (and the BLAS's code path). Here:
//   forward   the layers of mlp.h (a chain of fused multiply-adds per output): the same bits as the
//             inference kernels' fp32 path, on any path and thread count;
//   backward  per sample, dy -> dx through the same layer code (dx = dy W as y = x W^T with W's rows
//             as the "inputs"), ReLU masks from the saved activations; the weight and bias gradients
//             are sums over samples: each group of kGradGroup consecutive samples sums its own in sample
//             order (a fused multiply-add chain per entry), then the groups' sums are added in group
//             order. The groups are fixed by the sample count, not by the threads, so the gradients are
//             the same bits for any thread count and on the AVX-512 and portable paths.
// Layers (density hidden, density out, colour hidden, colour out), as dualnerf.fields.RadianceField:
//   h1 = relu(W0 f + b0); [h_sigma, geo] = W1 h1 + b1; h2 = relu(W2 [geo, sh] + b2); h_color = W3 h2 + b3.

namespace {

constexpr int64_t kTrainBlock = 128;    // samples per forward/backward block (activations stay in cache)
constexpr int64_t kGradGroup = 1024;    // samples per partial weight-gradient sum (a multiple of kTrainBlock)

int padded(int n) { return (n + kLanes - 1) / kLanes * kLanes; }

// The four layers in the forward layout (wt (in, out_pad), b (out_pad)); out of layers 0-2 from the next
// layer's inputs, as describe_mlps in inference.cpp.
struct Mlp {
  Layer layer[4];
  int n_sh, geo;
};

Mlp describe_train_mlp(const std::vector<at::Tensor>& t, int64_t n_features, int64_t n_sh) {
  TORCH_CHECK(t.size() == 8, "mlp_train: 8 MLP tensors expected (wt, b for 4 layers)");
  Mlp m;
  for (int i = 0; i < 4; ++i) {
    const auto& wt = t[2 * i];
    const auto& b = t[2 * i + 1];
    TORCH_CHECK(wt.dim() == 2 && wt.is_contiguous() && wt.scalar_type() == at::kFloat && b.dim() == 1 &&
                    b.is_contiguous() && b.size(0) == wt.size(1) && wt.size(1) % kLanes == 0 &&
                    wt.size(1) <= 8 * kLanes,
                "mlp_train: layer weights must be contiguous float32 (in, out padded to 16, <= 128) with a bias");
    m.layer[i] = {wt.data_ptr<float>(), b.data_ptr<float>(), static_cast<int>(wt.size(0)), 0,
                  static_cast<int>(wt.size(1))};
  }
  m.layer[0].out = m.layer[1].in;
  m.layer[2].out = m.layer[3].in;
  m.layer[3].out = 3;
  m.n_sh = static_cast<int>(n_sh);
  m.geo = m.layer[2].in - m.n_sh;
  m.layer[1].out = 1 + m.geo;
  TORCH_CHECK(m.layer[0].in == n_features && m.geo >= 0 && m.layer[1].out <= m.layer[1].out_pad &&
                  m.layer[0].out <= m.layer[0].out_pad && m.layer[2].out <= m.layer[2].out_pad,
              "mlp_train: inconsistent MLP shapes");
  return m;
}

// g (in x out_pad, row-major) += sum over rows r, in order, of x[r][k] * dy[r][:]: per entry a chain of
// fused multiply-adds over the rows. bias (out_pad) += sum over rows of dy[r][:] (plain additions).
void accumulate_portable(float* g, float* bias, int in, int out_pad, const float* x, int64_t ld_x, const float* dy,
                         int64_t ld_dy, int64_t rows) {
  for (int k = 0; k < in; ++k)
    for (int j = 0; j < out_pad; ++j) {
      float acc = g[k * out_pad + j];
      for (int64_t r = 0; r < rows; ++r) acc = std::fma(x[r * ld_x + k], dy[r * ld_dy + j], acc);
      g[k * out_pad + j] = acc;
    }
  for (int j = 0; j < out_pad; ++j) {
    float acc = bias[j];
    for (int64_t r = 0; r < rows; ++r) acc += dy[r * ld_dy + j];
    bias[j] = acc;
  }
}

#ifdef DUALNERF_HAVE_AVX2
// accumulate_portable for builds with the AVX2 flags (kernels/__init__.py isa_flags): KB inputs x outputs
// [col, col + 8 NV) in registers (tiles as mlp.h's layer_rows_avx2), per entry the same chain in the same
// row order, so the same bits.
template <int NV, int KB>
inline void accumulate_tile_avx2(float* g, int out_pad, int col, const float* x, int64_t ld_x, const float* dy,
                                 int64_t ld_dy, int64_t rows) {
  __m256 acc[KB][NV];
  DUALNERF_UNROLL
  for (int i = 0; i < KB; ++i)
    DUALNERF_UNROLL
    for (int v = 0; v < NV; ++v) acc[i][v] = _mm256_loadu_ps(g + i * out_pad + col + 8 * v);
  for (int64_t r = 0; r < rows; ++r) {
    __m256 d[NV];
    DUALNERF_UNROLL
    for (int v = 0; v < NV; ++v) d[v] = _mm256_loadu_ps(dy + r * ld_dy + col + 8 * v);
    DUALNERF_UNROLL
    for (int i = 0; i < KB; ++i) {
      const __m256 xs = _mm256_broadcast_ss(x + r * ld_x + i);
      DUALNERF_UNROLL
      for (int v = 0; v < NV; ++v) acc[i][v] = _mm256_fmadd_ps(xs, d[v], acc[i][v]);
    }
  }
  DUALNERF_UNROLL
  for (int i = 0; i < KB; ++i)
    DUALNERF_UNROLL
    for (int v = 0; v < NV; ++v) _mm256_storeu_ps(g + i * out_pad + col + 8 * v, acc[i][v]);
}

void accumulate_avx2(float* g, float* bias, int in, int out_pad, const float* x, int64_t ld_x, const float* dy,
                     int64_t ld_dy, int64_t rows) {
  for (int col = 0; col < out_pad; col += 16)
    for_tiles6(in, [&]<int KB>(int64_t k) {
      accumulate_tile_avx2<2, KB>(g + k * out_pad, out_pad, col, x + k, ld_x, dy, ld_dy, rows);
    });
  for (int v = 0; v < out_pad / 8; ++v) {
    __m256 acc = _mm256_loadu_ps(bias + 8 * v);
    for (int64_t r = 0; r < rows; ++r) acc = _mm256_add_ps(acc, _mm256_loadu_ps(dy + r * ld_dy + 8 * v));
    _mm256_storeu_ps(bias + 8 * v, acc);
  }
}
#endif

#ifdef DUALNERF_HAVE_AVX512
// accumulate_portable with NV vectors of outputs and KB inputs at a time in registers (each dy vector is
// loaded once per row and used for KB inputs); per entry the same chain, in the same row order.
template <int NV, int KB>
__attribute__((target("avx512f"))) inline void accumulate_tile_avx512(float* g, int out_pad, const float* x,
                                                                      int64_t ld_x, const float* dy, int64_t ld_dy,
                                                                      int64_t rows) {
  __m512 acc[KB][NV];
  for (int i = 0; i < KB; ++i)
    for (int v = 0; v < NV; ++v) acc[i][v] = _mm512_loadu_ps(g + i * out_pad + kLanes * v);
  for (int64_t r = 0; r < rows; ++r) {
    __m512 d[NV];
    for (int v = 0; v < NV; ++v) d[v] = _mm512_loadu_ps(dy + r * ld_dy + kLanes * v);
    for (int i = 0; i < KB; ++i) {
      const __m512 xs = _mm512_set1_ps(x[r * ld_x + i]);
      for (int v = 0; v < NV; ++v) acc[i][v] = _mm512_fmadd_ps(xs, d[v], acc[i][v]);
    }
  }
  for (int i = 0; i < KB; ++i)
    for (int v = 0; v < NV; ++v) _mm512_storeu_ps(g + i * out_pad + kLanes * v, acc[i][v]);
}

template <int NV>
__attribute__((target("avx512f"))) void accumulate_avx512(float* g, float* bias, int in, int out_pad, const float* x,
                                                          int64_t ld_x, const float* dy, int64_t ld_dy, int64_t rows) {
  constexpr int KB = NV >= 4 ? 4 : 8;
  int k = 0;
  for (; k + KB <= in; k += KB) accumulate_tile_avx512<NV, KB>(g + k * out_pad, out_pad, x + k, ld_x, dy, ld_dy, rows);
  for (; k < in; ++k) accumulate_tile_avx512<NV, 1>(g + k * out_pad, out_pad, x + k, ld_x, dy, ld_dy, rows);
  for (int v = 0; v < NV; ++v) {
    __m512 acc = _mm512_loadu_ps(bias + kLanes * v);
    for (int64_t r = 0; r < rows; ++r) acc = _mm512_add_ps(acc, _mm512_loadu_ps(dy + r * ld_dy + kLanes * v));
    _mm512_storeu_ps(bias + kLanes * v, acc);
  }
}
#endif

void accumulate(float* g, float* bias, int in, int out_pad, const float* x, int64_t ld_x, const float* dy,
                int64_t ld_dy, int64_t rows, bool vector_path) {
#ifdef DUALNERF_HAVE_AVX512
  if (vector_path && avx512_available()) {
    switch (out_pad / kLanes) {
      case 1: return accumulate_avx512<1>(g, bias, in, out_pad, x, ld_x, dy, ld_dy, rows);
      case 2: return accumulate_avx512<2>(g, bias, in, out_pad, x, ld_x, dy, ld_dy, rows);
      case 4: return accumulate_avx512<4>(g, bias, in, out_pad, x, ld_x, dy, ld_dy, rows);
      case 8: return accumulate_avx512<8>(g, bias, in, out_pad, x, ld_x, dy, ld_dy, rows);
    }
  }
#endif
#ifdef DUALNERF_HAVE_AVX2
  if (vector_path && out_pad % 16 == 0) return accumulate_avx2(g, bias, in, out_pad, x, ld_x, dy, ld_dy, rows);
#endif
  accumulate_portable(g, bias, in, out_pad, x, ld_x, dy, ld_dy, rows);
}

// The same sums for a layer with few outputs (the density output's 16, the colour output's 3), in the
// transposed layout: gt (out x in_pad) += sum over rows of dy[r][j] * x[r][:], vectorised over the
// inputs (over the 16-padded outputs a row would give one vector of FMAs per 8 or 16 broadcast loads,
// or 3 useful lanes of 16). Per entry the same chain over the rows, so the same bits as `accumulate`
// would give. bias (out_pad; dy's padding columns are zeros) as there.
void accumulate_by_inputs_portable(float* gt, float* bias, int in, int in_pad, int out, int out_pad, const float* x,
                                   int64_t ld_x, const float* dy, int64_t ld_dy, int64_t rows) {
  for (int j = 0; j < out; ++j)
    for (int k = 0; k < in; ++k) {
      float acc = gt[j * in_pad + k];
      for (int64_t r = 0; r < rows; ++r) acc = std::fma(x[r * ld_x + k], dy[r * ld_dy + j], acc);
      gt[j * in_pad + k] = acc;
    }
  for (int j = 0; j < out_pad; ++j) {
    float acc = bias[j];
    for (int64_t r = 0; r < rows; ++r) acc += dy[r * ld_dy + j];
    bias[j] = acc;
  }
}

constexpr int kMaxByInputs = 16;    // layers with at most this many outputs accumulate by inputs

#ifdef DUALNERF_HAVE_AVX2
// accumulate_by_inputs_portable for builds with the AVX2 flags: JB outputs x inputs [col, col + 8 NV) of gt
// in registers (inputs past `in` read as zeros, as the AVX-512 code's masked loads; tiles as mlp.h's
// layer_rows_avx2); per entry the same chain over the rows, so the same bits.
template <int NV, int JB>
inline void accumulate_by_inputs_tile_avx2(float* gt, int in_pad, int col, const __m256i* lanes, bool full,
                                           const float* x, int64_t ld_x, const float* dy, int64_t ld_dy,
                                           int64_t rows) {
  __m256 acc[JB][NV];
  DUALNERF_UNROLL
  for (int j = 0; j < JB; ++j)
    DUALNERF_UNROLL
    for (int v = 0; v < NV; ++v) acc[j][v] = _mm256_loadu_ps(gt + j * in_pad + col + 8 * v);
  for (int64_t r = 0; r < rows; ++r) {
    __m256 xs[NV];
    DUALNERF_UNROLL
    for (int v = 0; v < NV; ++v) {
      const float* row = x + r * ld_x + col + 8 * v;
      xs[v] = full ? _mm256_loadu_ps(row) : _mm256_maskload_ps(row, lanes[v]);
    }
    DUALNERF_UNROLL
    for (int j = 0; j < JB; ++j) {
      const __m256 d = _mm256_broadcast_ss(dy + r * ld_dy + j);
      DUALNERF_UNROLL
      for (int v = 0; v < NV; ++v) acc[j][v] = _mm256_fmadd_ps(xs[v], d, acc[j][v]);
    }
  }
  DUALNERF_UNROLL
  for (int j = 0; j < JB; ++j)
    DUALNERF_UNROLL
    for (int v = 0; v < NV; ++v) _mm256_storeu_ps(gt + j * in_pad + col + 8 * v, acc[j][v]);
}

void accumulate_by_inputs_avx2(float* gt, float* bias, int in, int in_pad, int out, int out_pad, const float* x,
                               int64_t ld_x, const float* dy, int64_t ld_dy, int64_t rows) {
  for (int col = 0; col < in_pad; col += 16) {
    const __m256i lanes[2] = {first_lanes8(in - col), first_lanes8(in - col - 8)};
    const bool full = col + 16 <= in;
    for_tiles6(out, [&]<int JB>(int64_t j) {
      accumulate_by_inputs_tile_avx2<2, JB>(gt + j * in_pad, in_pad, col, lanes, full, x, ld_x, dy + j, ld_dy, rows);
    });
  }
  for (int v = 0; v < out_pad / 8; ++v) {     // lane j: the portable loop's additions in its order
    __m256 acc = _mm256_loadu_ps(bias + 8 * v);
    for (int64_t r = 0; r < rows; ++r) acc = _mm256_add_ps(acc, _mm256_loadu_ps(dy + r * ld_dy + 8 * v));
    _mm256_storeu_ps(bias + 8 * v, acc);
  }
}
#endif

#ifdef DUALNERF_HAVE_AVX512
// JB outputs x NV input vectors of gt in registers; per row NV input loads, JB broadcasts, JB * NV FMAs.
template <int NV, int JB, bool kFullRows>
__attribute__((target("avx512f"))) inline void accumulate_by_inputs_tile_avx512(float* gt, int in_pad,
                                                                                const __mmask16* lanes,
                                                                                const float* x, int64_t ld_x,
                                                                                const float* dy, int64_t ld_dy,
                                                                                int64_t rows) {
  __m512 acc[JB][NV];
  DUALNERF_UNROLL
  for (int j = 0; j < JB; ++j) {
    DUALNERF_UNROLL
    for (int v = 0; v < NV; ++v) acc[j][v] = _mm512_loadu_ps(gt + j * in_pad + kLanes * v);
  }
  for (int64_t r = 0; r < rows; ++r) {
    __m512 xs[NV];
    DUALNERF_UNROLL
    for (int v = 0; v < NV; ++v)
      xs[v] = kFullRows ? _mm512_loadu_ps(x + r * ld_x + kLanes * v)
                        : _mm512_maskz_loadu_ps(lanes[v], x + r * ld_x + kLanes * v);
    DUALNERF_UNROLL
    for (int j = 0; j < JB; ++j) {
      const __m512 d = _mm512_set1_ps(dy[r * ld_dy + j]);
      DUALNERF_UNROLL
      for (int v = 0; v < NV; ++v) acc[j][v] = _mm512_fmadd_ps(xs[v], d, acc[j][v]);
    }
  }
  DUALNERF_UNROLL
  for (int j = 0; j < JB; ++j) {
    DUALNERF_UNROLL
    for (int v = 0; v < NV; ++v) _mm512_storeu_ps(gt + j * in_pad + kLanes * v, acc[j][v]);
  }
}

template <int NV>
__attribute__((target("avx512f"))) void accumulate_by_inputs_avx512(float* gt, float* bias, int in, int in_pad,
                                                                    int out, int out_pad, const float* x,
                                                                    int64_t ld_x, const float* dy, int64_t ld_dy,
                                                                    int64_t rows) {
  constexpr int JB = NV >= 4 ? 4 : 8;
  __mmask16 lanes[NV];
  for (int v = 0; v < NV; ++v) lanes[v] = first_lanes(in - kLanes * v);
  // Rows without padding load whole vectors, without masks (before DUALNERF_UNROLL the masked tiles also
  // kept their accumulators in memory; benchmarks/kernel_spills.py shows both in registers now).
  auto tiles = [&](auto full) {
    constexpr bool kFull = decltype(full)::value;
    int j = 0;
    for (; j + JB <= out; j += JB)
      accumulate_by_inputs_tile_avx512<NV, JB, kFull>(gt + j * in_pad, in_pad, lanes, x, ld_x, dy + j, ld_dy, rows);
    if (out - j == 3) {
      accumulate_by_inputs_tile_avx512<NV, 3, kFull>(gt + j * in_pad, in_pad, lanes, x, ld_x, dy + j, ld_dy, rows);
      return;
    }
    for (; j + 2 <= out; j += 2)
      accumulate_by_inputs_tile_avx512<NV, 2, kFull>(gt + j * in_pad, in_pad, lanes, x, ld_x, dy + j, ld_dy, rows);
    for (; j < out; ++j)
      accumulate_by_inputs_tile_avx512<NV, 1, kFull>(gt + j * in_pad, in_pad, lanes, x, ld_x, dy + j, ld_dy, rows);
  };
  if (in == in_pad)
    tiles(std::true_type{});
  else
    tiles(std::false_type{});
  // The bias: one vector chain per 16 outputs over the rows (lane j: the same additions in the same order
  // as the portable loop).
  for (int v = 0; v < out_pad / kLanes; ++v) {
    __m512 acc = _mm512_loadu_ps(bias + kLanes * v);
    for (int64_t r = 0; r < rows; ++r) acc = _mm512_add_ps(acc, _mm512_loadu_ps(dy + r * ld_dy + kLanes * v));
    _mm512_storeu_ps(bias + kLanes * v, acc);
  }
}
#endif

void accumulate_by_inputs(float* gt, float* bias, int in, int in_pad, int out, int out_pad, const float* x,
                          int64_t ld_x, const float* dy, int64_t ld_dy, int64_t rows, bool vector_path) {
#ifdef DUALNERF_HAVE_AVX512
  if (vector_path && avx512_available()) {
    switch (in_pad / kLanes) {
      case 1: return accumulate_by_inputs_avx512<1>(gt, bias, in, in_pad, out, out_pad, x, ld_x, dy, ld_dy, rows);
      case 2: return accumulate_by_inputs_avx512<2>(gt, bias, in, in_pad, out, out_pad, x, ld_x, dy, ld_dy, rows);
      case 4: return accumulate_by_inputs_avx512<4>(gt, bias, in, in_pad, out, out_pad, x, ld_x, dy, ld_dy, rows);
    }
  }
#endif
#ifdef DUALNERF_HAVE_AVX2
  if (vector_path && in_pad % 16 == 0)
    return accumulate_by_inputs_avx2(gt, bias, in, in_pad, out, out_pad, x, ld_x, dy, ld_dy, rows);
#endif
  accumulate_by_inputs_portable(gt, bias, in, in_pad, out, out_pad, x, ld_x, dy, ld_dy, rows);
}

// Zeroes dy[r][j] where the layer's saved output act[r][j] (after its ReLU) is not positive: the ReLU's
// backward.
void relu_backward(float* dy, int64_t ld_dy, const float* act, int64_t ld_act, int64_t rows, int width) {
  for (int64_t r = 0; r < rows; ++r) {     // a select, not a branch: the signs are random
    float* d = dy + r * ld_dy;
    const float* a = act + r * ld_act;
    for (int j = 0; j < width; ++j) d[j] = a[j] > 0.0f ? d[j] : 0.0f;
  }
}

const float* sh_row(const float* sh, const int64_t* sh_index, int64_t i, int n_sh) {
  return sh + (sh_index ? sh_index[i] : i) * n_sh;
}

}  // namespace

// (h_sigma (M,), h_color (M, 3), hidden_density (M, H0p), color_in (M, geo + S), hidden_color (M, H2p)):
// the MLPs' outputs and the activations mlp_train_backward reads. Row i's direction features are
// sh[i], or sh[sh_index[i]] with an index (one row per ray).
std::vector<at::Tensor> mlp_train_forward(at::Tensor features, at::Tensor sh,
                                          std::optional<at::Tensor> sh_index, std::vector<at::Tensor> mlp,
                                          bool vector_path) {
  TORCH_CHECK(features.dim() == 2 && features.scalar_type() == at::kFloat && features.device().is_cpu() &&
                  sh.dim() == 2 && sh.scalar_type() == at::kFloat,
              "mlp_train_forward: (M, F) features and (M or R, S) sh, float32 CPU");
  features = features.contiguous();
  sh = sh.contiguous();
  const int64_t m = features.size(0), n_features = features.size(1), n_sh = sh.size(1);
  at::Tensor index;
  if (sh_index.has_value()) {
    index = sh_index->contiguous();
    TORCH_CHECK(index.dim() == 1 && index.size(0) == m && index.scalar_type() == at::kLong,
                "mlp_train_forward: sh_index must be (M,) int64");
    if (m > 0)
      TORCH_CHECK(index.min().item<int64_t>() >= 0 && index.max().item<int64_t>() < sh.size(0),
                  "mlp_train_forward: sh_index out of range of sh's rows");
  } else {
    TORCH_CHECK(sh.size(0) == m, "mlp_train_forward: one sh row per sample without sh_index");
  }
  const Mlp net = describe_train_mlp(mlp, n_features, n_sh);
  const Layer* l = net.layer;
  const int64_t ld_h1 = l[0].out_pad, ld_c = l[2].in, ld_h2 = l[2].out_pad;
  auto h_sigma = features.new_empty({m});
  auto h_color = features.new_empty({m, 3});
  // The hidden activations' padding columns (width not a multiple of 16) must read as zeros in the
  // backward; every other entry is written below, so without padding the zero fill (two (M, 64) memsets,
  // ~4% of a training step) is skipped.
  auto hidden = [&](const Layer& layer, int64_t ld) {
    return layer.out == ld ? features.new_empty({m, ld}) : features.new_zeros({m, ld});
  };
  auto hidden_density = hidden(l[0], ld_h1);
  auto color_in = features.new_empty({m, ld_c});
  auto hidden_color = hidden(l[2], ld_h2);
  const float *fp = features.data_ptr<float>(), *shp = sh.data_ptr<float>();
  const int64_t* ip = index.defined() ? index.data_ptr<int64_t>() : nullptr;
  float *sp = h_sigma.data_ptr<float>(), *cp = h_color.data_ptr<float>(), *h1 = hidden_density.data_ptr<float>(),
        *ci = color_in.data_ptr<float>(), *h2 = hidden_color.data_ptr<float>();
  parallel_for(0, (m + kTrainBlock - 1) / kTrainBlock, 1, [&](int64_t block_begin, int64_t block_end) {
    std::vector<float> density_out(kTrainBlock * l[1].out_pad), rgb(kTrainBlock * l[3].out_pad);
    for (int64_t blk = block_begin; blk < block_end; ++blk) {
      const int64_t begin = blk * kTrainBlock, rows = std::min(m, begin + kTrainBlock) - begin;
      layer_rows(l[0], fp + begin * n_features, n_features, rows, h1 + begin * ld_h1, ld_h1, true, vector_path);
      layer_rows(l[1], h1 + begin * ld_h1, ld_h1, rows, density_out.data(), l[1].out_pad, false, vector_path);
      for (int64_t r = 0; r < rows; ++r) {
        const float* d = density_out.data() + r * l[1].out_pad;
        float* c = ci + (begin + r) * ld_c;
        sp[begin + r] = d[0];
        std::copy(d + 1, d + 1 + net.geo, c);
        const float* s = sh_row(shp, ip, begin + r, net.n_sh);
        std::copy(s, s + net.n_sh, c + net.geo);
      }
      layer_rows(l[2], ci + begin * ld_c, ld_c, rows, h2 + begin * ld_h2, ld_h2, true, vector_path);
      layer_rows(l[3], h2 + begin * ld_h2, ld_h2, rows, rgb.data(), l[3].out_pad, false, vector_path);
      for (int64_t r = 0; r < rows; ++r)
        for (int j = 0; j < 3; ++j) cp[3 * (begin + r) + j] = rgb[r * l[3].out_pad + j];
    }
  });
  return {h_sigma, h_color, hidden_density, color_in, hidden_color};
}

// The backward of mlp_train_forward: (grad_features (M, F), then per layer the weight gradient (out, in)
// and the bias gradient (out,), as the nn.Linear parameters).
// mlp: the forward layout (as mlp_train_forward); weights: each layer's nn.Linear weight zero-padded to
// (out, in_pad) (dx = dy W).
std::vector<at::Tensor> mlp_train_backward(at::Tensor grad_sigma, at::Tensor grad_color,
                                           at::Tensor features, at::Tensor hidden_density,
                                           at::Tensor color_in, at::Tensor hidden_color,
                                           std::vector<at::Tensor> mlp, std::vector<at::Tensor> weights,
                                           int64_t n_sh, bool vector_path) {
  const int64_t m = features.size(0), n_features = features.size(1);
  const Mlp net = describe_train_mlp(mlp, n_features, n_sh);
  const Layer* l = net.layer;
  TORCH_CHECK(weights.size() == 4, "mlp_train_backward: 4 padded weights expected");
  Layer back[4];     // dx = dy W: W's rows as the inputs of mlp.h's layer code, no bias
  std::vector<float> zeros(8 * kLanes, 0.0f);
  for (int i = 0; i < 4; ++i) {
    const auto& w = weights[i];
    TORCH_CHECK(w.dim() == 2 && w.is_contiguous() && w.scalar_type() == at::kFloat &&
                    w.size(0) == l[i].out && w.size(1) == padded(l[i].in) && w.size(1) <= 8 * kLanes,
                "mlp_train_backward: weight ", i, " must be its (out, in padded to 16) nn.Linear weight");
    back[i] = {w.data_ptr<float>(), zeros.data(), l[i].out, l[i].in, static_cast<int>(w.size(1))};
  }
  for (const auto* t : {&grad_sigma, &grad_color, &hidden_density, &color_in, &hidden_color})
    TORCH_CHECK(t->scalar_type() == at::kFloat && t->size(0) == m, "mlp_train_backward: float32, M rows");
  grad_sigma = grad_sigma.contiguous();
  grad_color = grad_color.contiguous();
  features = features.contiguous();
  const int64_t ld_h1 = l[0].out_pad, ld_c = l[2].in, ld_h2 = l[2].out_pad;
  TORCH_CHECK(hidden_density.is_contiguous() && hidden_density.size(1) == ld_h1 && color_in.is_contiguous() &&
                  color_in.size(1) == ld_c && hidden_color.is_contiguous() && hidden_color.size(1) == ld_h2 &&
                  grad_color.size(1) == 3,
              "mlp_train_backward: the activations of mlp_train_forward expected");
  // One partial sum of every weight and bias gradient per group of samples: layer i's weight gradient by
  // outputs, (in, out_pad) as the forward layout, or by inputs, (out, in_pad), for a layer with few outputs.
  bool by_inputs[4];
  int64_t offset[8], size = 0;
  for (int i = 0; i < 4; ++i) {
    by_inputs[i] = l[i].out <= kMaxByInputs;
    offset[2 * i] = size;
    size += by_inputs[i] ? static_cast<int64_t>(l[i].out) * padded(l[i].in) : static_cast<int64_t>(l[i].in) * l[i].out_pad;
    offset[2 * i + 1] = size;
    size += l[i].out_pad;
  }
  const int64_t n_groups = std::max<int64_t>(1, (m + kGradGroup - 1) / kGradGroup);
  auto partial = features.new_zeros({n_groups, size});
  auto grad_features = features.new_empty({m, n_features});
  const float *gs = grad_sigma.data_ptr<float>(), *gc = grad_color.data_ptr<float>(),
              *fp = features.data_ptr<float>(), *h1 = hidden_density.data_ptr<float>(),
              *ci = color_in.data_ptr<float>(), *h2 = hidden_color.data_ptr<float>();
  float *pp = partial.data_ptr<float>(), *gf = grad_features.data_ptr<float>();
  // Layer i's weight and bias gradient sums in group g += its inputs x (rows) times its output gradients dy.
  auto accumulate_layer = [&](int i, float* g, const float* x, int64_t ld_x, const float* dy, int64_t ld_dy,
                              int64_t rows) {
    if (by_inputs[i])
      accumulate_by_inputs(g + offset[2 * i], g + offset[2 * i + 1], l[i].in, padded(l[i].in), l[i].out, l[i].out_pad,
                           x, ld_x, dy, ld_dy, rows, vector_path);
    else
      accumulate(g + offset[2 * i], g + offset[2 * i + 1], l[i].in, l[i].out_pad, x, ld_x, dy, ld_dy, rows, vector_path);
  };
  parallel_for(0, n_groups, 1, [&](int64_t group_begin, int64_t group_end) {
    // Per block: the output gradients of layers 3, 2, 1, 0 (rows x out_pad, zero padding) and dx of layer 2.
    std::vector<float> d3(kTrainBlock * l[3].out_pad, 0.0f), d2(kTrainBlock * l[2].out_pad, 0.0f),
        d1(kTrainBlock * l[1].out_pad, 0.0f), d0(kTrainBlock * l[0].out_pad, 0.0f),
        dc(kTrainBlock * back[2].out_pad, 0.0f);
    for (int64_t group = group_begin; group < group_end; ++group) {
      float* g = pp + group * size;
      const int64_t group_stop = std::min(m, (group + 1) * kGradGroup);
      for (int64_t begin = group * kGradGroup; begin < group_stop; begin += kTrainBlock) {
        const int64_t rows = std::min(group_stop, begin + kTrainBlock) - begin;
        const float* a1 = h1 + begin * ld_h1;
        const float* a2 = h2 + begin * ld_h2;
        const float* c_in = ci + begin * ld_c;
        for (int64_t r = 0; r < rows; ++r)
          for (int j = 0; j < 3; ++j) d3[r * l[3].out_pad + j] = gc[3 * (begin + r) + j];
        accumulate_layer(3, g, a2, ld_h2, d3.data(), l[3].out_pad, rows);
        layer_rows(back[3], d3.data(), l[3].out_pad, rows, d2.data(), l[2].out_pad, false, vector_path);
        relu_backward(d2.data(), l[2].out_pad, a2, ld_h2, rows, l[2].out);
        accumulate_layer(2, g, c_in, ld_c, d2.data(), l[2].out_pad, rows);
        layer_rows(back[2], d2.data(), l[2].out_pad, rows, dc.data(), back[2].out_pad, false, vector_path);
        for (int64_t r = 0; r < rows; ++r) {
          float* d = d1.data() + r * l[1].out_pad;
          d[0] = gs[begin + r];
          std::copy(dc.data() + r * back[2].out_pad, dc.data() + r * back[2].out_pad + net.geo, d + 1);
        }
        accumulate_layer(1, g, a1, ld_h1, d1.data(), l[1].out_pad, rows);
        layer_rows(back[1], d1.data(), l[1].out_pad, rows, d0.data(), l[0].out_pad, false, vector_path);
        relu_backward(d0.data(), l[0].out_pad, a1, ld_h1, rows, l[0].out);
        accumulate_layer(0, g, fp + begin * n_features, n_features, d0.data(), l[0].out_pad, rows);
        layer_rows(back[0], d0.data(), l[0].out_pad, rows, gf + begin * n_features, n_features, false, vector_path);
      }
    }
  });
  // The groups' partial sums added in group order, entry by entry.
  auto total = partial[0].clone();
  float* tp = total.data_ptr<float>();
  parallel_for(0, size, 4096, [&](int64_t begin, int64_t end) {
    for (int64_t group = 1; group < n_groups; ++group) {
      const float* p = pp + group * size;
      for (int64_t e = begin; e < end; ++e) tp[e] += p[e];
    }
  });
  // (out, in) weight and (out,) bias gradients, as the nn.Linear parameters.
  std::vector<at::Tensor> out{grad_features};
  for (int i = 0; i < 4; ++i) {
    auto weight = total.narrow(0, offset[2 * i], offset[2 * i + 1] - offset[2 * i]);
    weight = by_inputs[i] ? weight.view({l[i].out, padded(l[i].in)}).narrow(1, 0, l[i].in)
                          : weight.view({l[i].in, l[i].out_pad}).narrow(1, 0, l[i].out).t();
    out.push_back(weight.contiguous());
    out.push_back(total.narrow(0, offset[2 * i + 1], l[i].out).clone());
  }
  return out;
}
