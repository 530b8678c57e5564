// The MLP layer code shared by the inference kernels (inference.cpp) and the training kernels
// (mlp_train.cpp): y = b + sum_k x_k W[:, k] per row, accumulated as a chain of fused multiply-adds in k
// order starting from the bias, on the AVX-512 path and the portable path alike (std::fma rounds exactly
// like the vector instruction): a row's result does not depend on the path, its block, its neighbours or
// the thread count.
#pragma once

#include "kernels.h"

namespace dualnerf {

struct Layer {
  const float* wt;   // (in, out_pad) row-major: W transposed, zero-padded columns
  const float* b;    // (out_pad), zero-padded
  int in, out, out_pad;
};

#ifdef DUALNERF_HAVE_AVX2
// AVX2 has 16 vector registers. Tiles of B = 6 rows (or inputs, or outputs) x 16 values keep 12
// accumulators, the 2 vectors they share and a broadcast in registers; a tile of all of a layer's outputs
// (up to 8 vectors of 8) spilled its accumulators to memory on every step.

// Calls tile.operator()<N>(i) on [i, i + N) for consecutive tiles covering [0, count): N = 6, then the
// rest as one tile of 4, 3, 2 or 1 (5 = 4 + 1).
template <typename Tile>
inline void for_tiles6(int64_t count, Tile&& tile) {
  int64_t i = 0;
  for (; i + 6 <= count; i += 6) tile.template operator()<6>(i);
  switch (count - i) {
    case 5: tile.template operator()<4>(i); tile.template operator()<1>(i + 4); break;
    case 4: tile.template operator()<4>(i); break;
    case 3: tile.template operator()<3>(i); break;
    case 2: tile.template operator()<2>(i); break;
    case 1: tile.template operator()<1>(i); break;
  }
}

// RB rows x outputs [col, col + 8 NV) in registers, for builds with the AVX2 flags (kernels/__init__.py
// isa_flags): the same chains as the scalar and AVX-512 code (bias first, then k in order, one rounding
// per fused multiply-add), so the same bits.
template <int NV, int RB>
inline void layer_tile_avx2(const Layer& l, int col, const float* in, int64_t ld_in, float* out, int64_t ld_out,
                            bool relu) {
  __m256 acc[RB][NV];
  DUALNERF_UNROLL
  for (int v = 0; v < NV; ++v) {
    const __m256 bias = _mm256_loadu_ps(l.b + col + 8 * v);
    DUALNERF_UNROLL
    for (int r = 0; r < RB; ++r) acc[r][v] = bias;
  }
  for (int k = 0; k < l.in; ++k) {
    __m256 w[NV];
    DUALNERF_UNROLL
    for (int v = 0; v < NV; ++v) w[v] = _mm256_loadu_ps(l.wt + k * l.out_pad + col + 8 * v);
    DUALNERF_UNROLL
    for (int r = 0; r < RB; ++r) {
      const __m256 x = _mm256_broadcast_ss(in + r * ld_in + k);
      DUALNERF_UNROLL
      for (int v = 0; v < NV; ++v) acc[r][v] = _mm256_fmadd_ps(x, w[v], acc[r][v]);
    }
  }
  const __m256 zero = _mm256_setzero_ps();
  DUALNERF_UNROLL
  for (int r = 0; r < RB; ++r) {
    float* y = out + r * ld_out + col;
    DUALNERF_UNROLL
    for (int v = 0; v < NV; ++v) {
      const __m256 value = relu ? _mm256_max_ps(acc[r][v], zero) : acc[r][v];
      const int left = l.out - col - 8 * v;
      if (left >= 8) {
        _mm256_storeu_ps(y + 8 * v, value);
      } else if (left > 0) {
        _mm256_maskstore_ps(y + 8 * v, first_lanes8(left), value);
      }
    }
  }
}

// Rows in tiles of 6 x 16 outputs; a layer with at most 8 outputs (the colour output's 3) in tiles of 6 x 8.
inline void layer_rows_avx2(const Layer& l, const float* in, int64_t ld_in, int64_t rows, float* out,
                            int64_t ld_out, bool relu) {
  for_tiles6(rows, [&]<int RB>(int64_t r) {
    if (l.out <= 8) return layer_tile_avx2<1, RB>(l, 0, in + r * ld_in, ld_in, out + r * ld_out, ld_out, relu);
    for (int col = 0; col < l.out; col += 16)
      layer_tile_avx2<2, RB>(l, col, in + r * ld_in, ld_in, out + r * ld_out, ld_out, relu);
  });
}
#endif

// Rows [0, rows) of out = relu?(in @ wt + b), scalar code.
inline void layer_rows_portable(const Layer& l, const float* in, int64_t ld_in, int64_t rows, float* out, int64_t ld_out,
                         bool relu) {
  for (int64_t r = 0; r < rows; ++r) {
    const float* x = in + r * ld_in;
    float* y = out + r * ld_out;
    for (int j = 0; j < l.out; ++j) {
      float acc = l.b[j];
      for (int k = 0; k < l.in; ++k) acc = std::fma(x[k], l.wt[k * l.out_pad + j], acc);
      y[j] = relu ? (acc > 0.0f ? acc : 0.0f) : acc;
    }
  }
}

#ifdef DUALNERF_HAVE_AVX512

// RB rows x NV vectors of outputs held in registers; each weight vector is loaded once per k and reused
// for the RB rows.
template <int NV, int RB>
__attribute__((target("avx512f"))) inline void layer_tile_avx512(const Layer& l, const float* in, int64_t ld_in,
                                                                 float* out, int64_t ld_out, bool relu) {
  __m512 acc[RB][NV];
  for (int v = 0; v < NV; ++v) {
    const __m512 bias = _mm512_loadu_ps(l.b + kLanes * v);
    for (int r = 0; r < RB; ++r) acc[r][v] = bias;
  }
  for (int k = 0; k < l.in; ++k) {
    __m512 w[NV];
    for (int v = 0; v < NV; ++v) w[v] = _mm512_loadu_ps(l.wt + k * l.out_pad + kLanes * v);
    for (int r = 0; r < RB; ++r) {
      const __m512 x = _mm512_set1_ps(in[r * ld_in + k]);
      for (int v = 0; v < NV; ++v) acc[r][v] = _mm512_fmadd_ps(x, w[v], acc[r][v]);
    }
  }
  const __m512 zero = _mm512_setzero_ps();
  for (int r = 0; r < RB; ++r)
    for (int v = 0; v < NV; ++v) {
      const __m512 y = relu ? _mm512_max_ps(acc[r][v], zero) : acc[r][v];
      const int left = l.out - kLanes * v;
      const __mmask16 mask = first_lanes(left);
      _mm512_mask_storeu_ps(out + r * ld_out + kLanes * v, mask, y);
    }
}

template <int NV>
__attribute__((target("avx512f"))) void layer_rows_avx512(const Layer& l, const float* in, int64_t ld_in,
                                                          int64_t rows, float* out, int64_t ld_out, bool relu) {
  constexpr int RB = NV >= 4 ? 4 : 8;
  int64_t r = 0;
  for (; r + RB <= rows; r += RB) layer_tile_avx512<NV, RB>(l, in + r * ld_in, ld_in, out + r * ld_out, ld_out, relu);
  for (; r < rows; ++r) layer_tile_avx512<NV, 1>(l, in + r * ld_in, ld_in, out + r * ld_out, ld_out, relu);
}

#endif

// vector_path (the caller's DUALNERF_KERNEL_VECTOR): the AVX-512 tiles where the CPU has them, else the AVX2
// tiles where the build has them (kernels/__init__.py isa_flags); off: the scalar code. All the same bits.
inline void layer_rows(const Layer& l, const float* in, int64_t ld_in, int64_t rows, float* out, int64_t ld_out, bool relu,
                bool vector_path) {
#ifdef DUALNERF_HAVE_AVX512
  if (vector_path && avx512_available()) {
    switch (l.out_pad / kLanes) {
      case 1: return layer_rows_avx512<1>(l, in, ld_in, rows, out, ld_out, relu);
      case 2: return layer_rows_avx512<2>(l, in, ld_in, rows, out, ld_out, relu);
      case 4: return layer_rows_avx512<4>(l, in, ld_in, rows, out, ld_out, relu);
      case 8: return layer_rows_avx512<8>(l, in, ld_in, rows, out, ld_out, relu);
    }
  }
#endif
#ifdef DUALNERF_HAVE_AVX2
  if (vector_path && l.out_pad % 16 == 0) return layer_rows_avx2(l, in, ld_in, rows, out, ld_out, relu);
#endif
  layer_rows_portable(l, in, ld_in, rows, out, ld_out, relu);
}

}  // namespace dualnerf
