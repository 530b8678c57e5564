// Fused feature-grid look-ups for dualnerf.encoding (dense trilinear grids + bilinear xy/xz/yz planes).
//
// One pass over the points computes every table's interpolation, instead of one F.grid_sample call per
// table with its (C, M) intermediate, transpose and concatenation. Tables are read in channels-last
// layout (a point's C features at one corner are adjacent), so a corner costs one cache line.
// Semantics equal F.grid_sample(mode="bilinear", padding_mode="border", align_corners=True): the
// coordinate in [-1, 1] maps to (c + 1) / 2 * (size - 1), clamped to [0, size - 1].
//
// Forward: parallel over points (each output row written by one thread: deterministic).
// Backward: parallel over tables; each table's gradient is accumulated by one thread in point order,
// so there are no races and the sums are bit-for-bit repeatable.
#include "kernels.h"

using namespace dualnerf;

// Interpolates table `t` for points [begin, end) into out[:, t.column : t.column + C]. C is a template
// parameter so the per-corner channel loop unrolls.
template <int C>
void forward_table(const Table& t, const float* table, const float* xp, float* op, int64_t n_out, int64_t begin,
                   int64_t end, int64_t row0 = 0) {
  for (int64_t i = begin; i < end; ++i) {
    float acc[C] = {};
    corners(t, xp + 3 * i, [&](int64_t offset, float w) {
      for (int j = 0; j < C; ++j) acc[j] += w * table[offset + j];
    });
    float* oi = op + n_out * (i - row0) + t.column;
    for (int j = 0; j < C; ++j) oi[j] = acc[j];
  }
}

void forward_any(const Table& t, const float* table, const float* xp, float* op, int64_t n_out, int64_t begin,
                 int64_t end, int64_t row0 = 0) {
  switch (t.channels) {
    case 1: return forward_table<1>(t, table, xp, op, n_out, begin, end, row0);
    case 2: return forward_table<2>(t, table, xp, op, n_out, begin, end, row0);
    case 4: return forward_table<4>(t, table, xp, op, n_out, begin, end, row0);
    case 8: return forward_table<8>(t, table, xp, op, n_out, begin, end, row0);
  }
  TORCH_CHECK(false, "grid encoding kernel: features per table must be 1, 2, 4 or 8");
}

// The dual field's two fields (same architecture, same points): every corner's index and weight is
// computed once and applied to both fields' tables. Each output equals encode_forward's for that field
// bit for bit (the same operations per field in the same order).
template <int C>
void forward_table_pair(const Table& t, const float* table_a, const float* table_b, const float* xp, float* oa,
                        float* ob, int64_t n_out, int64_t begin, int64_t end, int64_t row0 = 0) {
  for (int64_t i = begin; i < end; ++i) {
    float acc_a[C] = {}, acc_b[C] = {};
    corners(t, xp + 3 * i, [&](int64_t offset, float w) {
      for (int j = 0; j < C; ++j) acc_a[j] += w * table_a[offset + j];
      for (int j = 0; j < C; ++j) acc_b[j] += w * table_b[offset + j];
    });
    for (int j = 0; j < C; ++j) oa[n_out * (i - row0) + t.column + j] = acc_a[j];
    for (int j = 0; j < C; ++j) ob[n_out * (i - row0) + t.column + j] = acc_b[j];
  }
}

// ---- Look-ups of 16 points at once (AVX-512 gathers) ----
//
// A look-up is ~60 scalar instructions per table and point (coordinates, weights, corner indices, loads):
// the profile had it instruction-bound, not memory-bound (the tables sit in the last-level cache). Here
// 16 points go through the same operations lane by lane, in the same order (multiply, then add: the
// build has no contraction), so every output equals the scalar code's bit for bit (tested). Tables of
// 2 features only (the fields' layout), with int32 offsets (tables below 2^31 floats); the rest of a
// range, and every other table, runs the scalar code.

namespace {

constexpr int64_t kLookupLanes = 16;

bool vector_lookup_applies(const Table& t) {
  return t.channels == 2 && table_cells(t) * t.stride < (int64_t{1} << 31);
}

// Coordinates of points [begin, begin + n) as three arrays (x's, y's, z's): what the 16-lane code loads.
std::vector<float> coordinate_arrays(const float* xp, int64_t begin, int64_t n) {
  std::vector<float> xs(3 * n);
  for (int64_t i = 0; i < n; ++i)
    for (int a = 0; a < 3; ++a) xs[a * n + i] = xp[3 * (begin + i) + a];
  return xs;
}

#ifdef DUALNERF_HAVE_AVX512

struct AxisV {
  __m512i i0;
  __m512 f;
};

// axis_coord on 16 lanes: max(p, 0) gives 0 for NaN as the scalar test does, and +0 for -0.
__attribute__((target("avx512f"))) inline AxisV axis_coord_v(__m512 c, int64_t size) {
  const __m512 top = _mm512_set1_ps(static_cast<float>(size - 1));
  __m512 p = _mm512_mul_ps(_mm512_mul_ps(_mm512_add_ps(c, _mm512_set1_ps(1.0f)), _mm512_set1_ps(0.5f)), top);
  p = _mm512_min_ps(_mm512_max_ps(p, _mm512_setzero_ps()), top);
  const __m512i i0 = _mm512_min_epi32(_mm512_cvttps_epi32(p), _mm512_set1_epi32(static_cast<int>(size - 2)));
  return {i0, _mm512_sub_ps(p, _mm512_cvtepi32_ps(i0))};
}

// A corner's two features (adjacent floats) for 16 points, gathered as 8-byte pairs: two 8-lane gathers
// load what two 16-lane float gathers did with half the loads (a gather costs one load per lane), then
// split into feature 0 and feature 1 of the 16 lanes.
// The values are the same floats, so everything computed from them is the same bits.
__attribute__((target("avx512f"))) inline void gather_features16(__m512i offset, const float* table, __m512& first,
                                                                 __m512& second) {
  const __m512i even = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30);
  const __m512i odd = _mm512_setr_epi32(1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29, 31);
  const __m512 lo = _mm512_castpd_ps(_mm512_i32gather_pd(_mm512_castsi512_si256(offset), table, 4));
  const __m512 hi = _mm512_castpd_ps(_mm512_i32gather_pd(_mm512_extracti64x4_epi64(offset, 1), table, 4));
  first = _mm512_permutex2var_ps(lo, even, hi);
  second = _mm512_permutex2var_ps(lo, odd, hi);
}

// One corner (offset vector, weight vector) into the accumulators of one or two tables.
template <bool Pair>
__attribute__((target("avx512f"))) inline void gather_corner(__m512i offset, __m512 w, const float* ta,
                                                             const float* tb, __m512 acc[4]) {
  __m512 f0, f1;
  gather_features16(offset, ta, f0, f1);
  acc[0] = _mm512_add_ps(acc[0], _mm512_mul_ps(w, f0));
  acc[1] = _mm512_add_ps(acc[1], _mm512_mul_ps(w, f1));
  if (Pair) {
    gather_features16(offset, tb, f0, f1);
    acc[2] = _mm512_add_ps(acc[2], _mm512_mul_ps(w, f0));
    acc[3] = _mm512_add_ps(acc[3], _mm512_mul_ps(w, f1));
  }
}

// The two features of 16 points (lane i's at out + rows[i]), written as 8-byte pairs: two 8-lane scatters
// instead of two 16-lane ones (half the stores).
__attribute__((target("avx512f"))) inline void scatter_features16(float* out, __m512i rows, __m512 first,
                                                                  __m512 second) {
  const __m512i low = _mm512_setr_epi32(0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21, 6, 22, 7, 23);
  const __m512i high = _mm512_setr_epi32(8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15, 31);
  _mm512_i32scatter_pd(out, _mm512_castsi512_si256(rows), _mm512_castps_pd(_mm512_permutex2var_ps(first, low, second)),
                       4);
  _mm512_i32scatter_pd(out, _mm512_extracti64x4_epi64(rows, 1),
                       _mm512_castps_pd(_mm512_permutex2var_ps(first, high, second)), 4);
}

// The corners of 16 points in table t: offsets (floats from the table's start, t.stride apart per cell)
// and weights, in the order of the scalar corners(); returns their count (8 for a grid, 4 for a plane).
__attribute__((target("avx512f"))) inline int corners16(const Table& t, const float* xs, int64_t stride,
                                                        __m512i off[8], __m512 w[8]) {
  const int r = static_cast<int>(t.res), c = static_cast<int>(t.stride);
  const __m512 one = _mm512_set1_ps(1.0f);
  if (t.kind == 3) {
    const AxisV ax = axis_coord_v(_mm512_loadu_ps(xs), r), ay = axis_coord_v(_mm512_loadu_ps(xs + stride), r),
                az = axis_coord_v(_mm512_loadu_ps(xs + 2 * stride), r);
    const __m512i rr = _mm512_set1_epi32(r);
    const __m512i base = _mm512_mullo_epi32(
        _mm512_add_epi32(_mm512_mullo_epi32(_mm512_add_epi32(_mm512_mullo_epi32(az.i0, rr), ay.i0), rr), ax.i0),
        _mm512_set1_epi32(c));
    const __m512i sx = _mm512_set1_epi32(c), sy = _mm512_set1_epi32(c * r), sz = _mm512_set1_epi32(c * r * r);
    const __m512 wx[2] = {_mm512_sub_ps(one, ax.f), ax.f}, wy[2] = {_mm512_sub_ps(one, ay.f), ay.f},
                 wz[2] = {_mm512_sub_ps(one, az.f), az.f};
    int n = 0;
    for (int dz = 0; dz < 2; ++dz)
      for (int dy = 0; dy < 2; ++dy) {
        const __m512 wzy = _mm512_mul_ps(wz[dz], wy[dy]);
        __m512i row = base;
        if (dz) row = _mm512_add_epi32(row, sz);
        if (dy) row = _mm512_add_epi32(row, sy);
        off[n] = row;
        w[n++] = _mm512_mul_ps(wzy, wx[0]);
        off[n] = _mm512_add_epi32(row, sx);
        w[n++] = _mm512_mul_ps(wzy, wx[1]);
      }
    return n;
  }
  const AxisV au = axis_coord_v(_mm512_loadu_ps(xs + t.a0 * stride), r),
              av = axis_coord_v(_mm512_loadu_ps(xs + t.a1 * stride), r);
  const __m512i base = _mm512_mullo_epi32(_mm512_add_epi32(_mm512_mullo_epi32(av.i0, _mm512_set1_epi32(r)), au.i0),
                                          _mm512_set1_epi32(c));
  const __m512i su = _mm512_set1_epi32(c), sv = _mm512_set1_epi32(c * r);
  const __m512 u0 = _mm512_sub_ps(one, au.f), v0 = _mm512_sub_ps(one, av.f);
  off[0] = base;
  w[0] = _mm512_mul_ps(v0, u0);
  off[1] = _mm512_add_epi32(base, su);
  w[1] = _mm512_mul_ps(v0, au.f);
  off[2] = _mm512_add_epi32(base, sv);
  w[2] = _mm512_mul_ps(av.f, u0);
  off[3] = _mm512_add_epi32(_mm512_add_epi32(base, sv), su);
  w[3] = _mm512_mul_ps(av.f, au.f);
  return 4;
}

// Table t (2 features) for the 16 points whose coordinates are xs[0..2][0..15] (structure of arrays),
// written to rows out + lane * n_out + t.column (and out_b likewise for the second table).
template <bool Pair>
__attribute__((target("avx512f"))) void lookup16(const Table& t, const float* ta, const float* tb, const float* xs,
                                                 int64_t stride, float* oa, float* ob, int64_t n_out) {
  __m512i off[8];
  __m512 w[8];
  const int n = corners16(t, xs, stride, off, w);
  __m512 acc[4] = {_mm512_setzero_ps(), _mm512_setzero_ps(), _mm512_setzero_ps(), _mm512_setzero_ps()};
  for (int k = 0; k < n; ++k) gather_corner<Pair>(off[k], w[k], ta, tb, acc);
  const __m512i rows = _mm512_mullo_epi32(_mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15),
                                          _mm512_set1_epi32(static_cast<int>(n_out)));
  scatter_features16(oa + t.column, rows, acc[0], acc[1]);
  if (Pair) scatter_features16(ob + t.column, rows, acc[2], acc[3]);
}

// corners16 into plain arrays (the backward's scalar additions read them lane by lane).
__attribute__((target("avx512f"))) inline int corners16_to_arrays(const Table& t, const float* xs, int64_t stride,
                                                                  int32_t offsets[8][16], float weights[8][16]) {
  __m512i off[8];
  __m512 w[8];
  const int n = corners16(t, xs, stride, off, w);
  for (int k = 0; k < n; ++k) {
    _mm512_storeu_si512(offsets[k], off[k]);
    _mm512_storeu_ps(weights[k], w[k]);
  }
  return n;
}

#endif

#ifdef DUALNERF_HAVE_AVX2
// ---- The same look-ups 8 points at a time (AVX2, for CPUs without AVX-512) ----
// Lane by lane the operations of corners16 / lookup16 in their order (no contraction), so the same bits.
// Written out again rather than templated over the vector width: the AVX-512 code is compiled under
// target("avx512f"), which a shared template would carry into code an AVX2-only CPU runs.

struct AxisV8 {
  __m256i i0;
  __m256 f;
};

inline AxisV8 axis_coord_v8(__m256 c, int64_t size) {
  const __m256 top = _mm256_set1_ps(static_cast<float>(size - 1));
  __m256 p = _mm256_mul_ps(_mm256_mul_ps(_mm256_add_ps(c, _mm256_set1_ps(1.0f)), _mm256_set1_ps(0.5f)), top);
  p = _mm256_min_ps(_mm256_max_ps(p, _mm256_setzero_ps()), top);    // max: NaN and -0 -> +0, as the scalar test
  const __m256i i0 = _mm256_min_epi32(_mm256_cvttps_epi32(p), _mm256_set1_epi32(static_cast<int>(size - 2)));
  return {i0, _mm256_sub_ps(p, _mm256_cvtepi32_ps(i0))};
}

inline int corners8(const Table& t, const float* xs, int64_t stride, __m256i off[8], __m256 w[8]) {
  const int r = static_cast<int>(t.res), c = static_cast<int>(t.stride);
  const __m256 one = _mm256_set1_ps(1.0f);
  if (t.kind == 3) {
    const AxisV8 ax = axis_coord_v8(_mm256_loadu_ps(xs), r), ay = axis_coord_v8(_mm256_loadu_ps(xs + stride), r),
                 az = axis_coord_v8(_mm256_loadu_ps(xs + 2 * stride), r);
    const __m256i rr = _mm256_set1_epi32(r);
    const __m256i base = _mm256_mullo_epi32(
        _mm256_add_epi32(_mm256_mullo_epi32(_mm256_add_epi32(_mm256_mullo_epi32(az.i0, rr), ay.i0), rr), ax.i0),
        _mm256_set1_epi32(c));
    const __m256i sx = _mm256_set1_epi32(c), sy = _mm256_set1_epi32(c * r), sz = _mm256_set1_epi32(c * r * r);
    const __m256 wx[2] = {_mm256_sub_ps(one, ax.f), ax.f}, wy[2] = {_mm256_sub_ps(one, ay.f), ay.f},
                 wz[2] = {_mm256_sub_ps(one, az.f), az.f};
    int n = 0;
    for (int dz = 0; dz < 2; ++dz)
      for (int dy = 0; dy < 2; ++dy) {
        const __m256 wzy = _mm256_mul_ps(wz[dz], wy[dy]);
        __m256i row = base;
        if (dz) row = _mm256_add_epi32(row, sz);
        if (dy) row = _mm256_add_epi32(row, sy);
        off[n] = row;
        w[n++] = _mm256_mul_ps(wzy, wx[0]);
        off[n] = _mm256_add_epi32(row, sx);
        w[n++] = _mm256_mul_ps(wzy, wx[1]);
      }
    return n;
  }
  const AxisV8 au = axis_coord_v8(_mm256_loadu_ps(xs + t.a0 * stride), r),
               av = axis_coord_v8(_mm256_loadu_ps(xs + t.a1 * stride), r);
  const __m256i base = _mm256_mullo_epi32(_mm256_add_epi32(_mm256_mullo_epi32(av.i0, _mm256_set1_epi32(r)), au.i0),
                                          _mm256_set1_epi32(c));
  const __m256i su = _mm256_set1_epi32(c), sv = _mm256_set1_epi32(c * r);
  const __m256 u0 = _mm256_sub_ps(one, au.f), v0 = _mm256_sub_ps(one, av.f);
  off[0] = base;
  w[0] = _mm256_mul_ps(v0, u0);
  off[1] = _mm256_add_epi32(base, su);
  w[1] = _mm256_mul_ps(v0, au.f);
  off[2] = _mm256_add_epi32(base, sv);
  w[2] = _mm256_mul_ps(av.f, u0);
  off[3] = _mm256_add_epi32(_mm256_add_epi32(base, sv), su);
  w[3] = _mm256_mul_ps(av.f, au.f);
  return 4;
}

// A corner's two features for 8 points: two 4-lane gathers of 8-byte pairs, split into feature 0 and 1.
inline void gather_features8(__m256i offset, const float* table, __m256& first, __m256& second) {
  const __m256 lo = _mm256_castpd_ps(_mm256_i32gather_pd(reinterpret_cast<const double*>(table),
                                                         _mm256_castsi256_si128(offset), 4));
  const __m256 hi = _mm256_castpd_ps(_mm256_i32gather_pd(reinterpret_cast<const double*>(table),
                                                         _mm256_extracti128_si256(offset, 1), 4));
  // lo = a0 b0 a1 b1 | a2 b2 a3 b3, hi = a4 b4 a5 b5 | a6 b6 a7 b7
  const __m256 evens = _mm256_shuffle_ps(lo, hi, _MM_SHUFFLE(2, 0, 2, 0));   // a0 a1 a4 a5 | a2 a3 a6 a7
  const __m256 odds = _mm256_shuffle_ps(lo, hi, _MM_SHUFFLE(3, 1, 3, 1));
  first = _mm256_castpd_ps(_mm256_permute4x64_pd(_mm256_castps_pd(evens), _MM_SHUFFLE(3, 1, 2, 0)));
  second = _mm256_castpd_ps(_mm256_permute4x64_pd(_mm256_castps_pd(odds), _MM_SHUFFLE(3, 1, 2, 0)));
}

// Tables larger than a core's L2 (512 KB on the EPYC measured below) are swept before they are gathered;
// smaller ones mostly hit in cache. A/B on that EPYC (1 thread, a campsite render's kernel calls replayed):
// sweeping every table, those over 256 KB or over 1 MB gave the same within noise, over 4 MB less.
constexpr int64_t kPrefetchTableBytes = int64_t{512} << 10;

// Requests (prefetcht0) the cache lines of the corners of points [0, n) in table t (and tb, a second
// field's separate table): per corner pair adjacent along the first axis, its first float and the pair's
// last. lookup_range sweeps a table's points with this before it gathers them. On an AVX2-only AMD EPYC
// (Zen 3) the misses were ~47% of an f_S render (benchmarks.profile_render_cache): a gather waits for its
// lines, and the out-of-order window reaches only a group or two of 8 points ahead. Paired runs there:
// renders 1.10-1.24x (f_S) and 1.18-1.32x (dual field) faster; the first float alone gained 1.09-1.10x,
// prefetcht1 (into L2) 1.03-1.20x.
// Nothing read changes, so the bits do not. The AVX-512 path does not sweep: on the Intel host where it
// was measured, prefetching the forward's rows made the look-ups slower (docs/design/kernels.md).
inline void prefetch_table8(const Table& t, const float* ta, const float* tb, const float* xs, int64_t n) {
  const int64_t span = t.stride + t.channels - 1;
  for (int64_t i = 0; i < n; i += 8) {
    __m256i off[8];
    __m256 w[8];
    const int corners = corners8(t, xs + i, n, off, w);
    alignas(32) int32_t lanes[8];
    for (int k = 0; k < corners; k += 2) {
      _mm256_store_si256(reinterpret_cast<__m256i*>(lanes), off[k]);
      for (int lane = 0; lane < 8; ++lane) {
        _mm_prefetch(reinterpret_cast<const char*>(ta + lanes[lane]), _MM_HINT_T0);
        _mm_prefetch(reinterpret_cast<const char*>(ta + lanes[lane] + span), _MM_HINT_T0);
        if (tb) {
          _mm_prefetch(reinterpret_cast<const char*>(tb + lanes[lane]), _MM_HINT_T0);
          _mm_prefetch(reinterpret_cast<const char*>(tb + lanes[lane] + span), _MM_HINT_T0);
        }
      }
    }
  }
}

template <bool Pair>
void lookup8(const Table& t, const float* ta, const float* tb, const float* xs, int64_t stride, float* oa, float* ob,
             int64_t n_out) {
  __m256i off[8];
  __m256 w[8];
  const int n = corners8(t, xs, stride, off, w);
  __m256 acc[4] = {_mm256_setzero_ps(), _mm256_setzero_ps(), _mm256_setzero_ps(), _mm256_setzero_ps()};
  for (int k = 0; k < n; ++k) {
    __m256 f0, f1;
    gather_features8(off[k], ta, f0, f1);
    acc[0] = _mm256_add_ps(acc[0], _mm256_mul_ps(w[k], f0));
    acc[1] = _mm256_add_ps(acc[1], _mm256_mul_ps(w[k], f1));
    if (Pair) {
      gather_features8(off[k], tb, f0, f1);
      acc[2] = _mm256_add_ps(acc[2], _mm256_mul_ps(w[k], f0));
      acc[3] = _mm256_add_ps(acc[3], _mm256_mul_ps(w[k], f1));
    }
  }
  alignas(32) float values[4][8];
  for (int a = 0; a < (Pair ? 4 : 2); ++a) _mm256_store_ps(values[a], acc[a]);
  for (int lane = 0; lane < 8; ++lane) {
    float* row = oa + lane * n_out + t.column;
    row[0] = values[0][lane];
    row[1] = values[1][lane];
    if (Pair) {
      float* row_b = ob + lane * n_out + t.column;
      row_b[0] = values[2][lane];
      row_b[1] = values[3][lane];
    }
  }
}
#endif

#if defined(DUALNERF_HAVE_AVX512) || defined(DUALNERF_HAVE_AVX2)
// ---- Prefetching the backward's gradient rows ----
constexpr int64_t kScatterAhead = 1;    // groups of 16 points whose gradient lines are requested ahead (1-8
                                        // measured: 1 was best, 1.3-1.9x the backward without)
constexpr int64_t kRing = 4;            // > kScatterAhead

struct alignas(64) GroupCorners {
  int32_t off[8][kLookupLanes];
  float w[8][kLookupLanes];
  int n;
};

// Requests the lines of a group's corners in a buffer laid out like table t (into L1: prefetcht0): per
// corner pair adjacent along the first axis, the first corner's first float and the second corner's last.
inline void prefetch_corners(float* buffer, const GroupCorners& c, const Table& t) {
  const int64_t span = t.stride + t.channels - 1;
  for (int k = 0; k < c.n; k += 2)
    for (int64_t lane = 0; lane < kLookupLanes; ++lane) {
      float* first = buffer + c.off[k][lane];
      _mm_prefetch(reinterpret_cast<const char*>(first), _MM_HINT_T0);
      _mm_prefetch(reinterpret_cast<const char*>(first + span), _MM_HINT_T0);
    }
}


// A group's corners (16 points) from the vector code this CPU runs: corners16 (AVX-512) or corners8 twice.
inline int group_corners(const Table& t, const float* xs, int64_t stride, GroupCorners& c) {
#ifdef DUALNERF_HAVE_AVX512
  if (avx512_available()) return corners16_to_arrays(t, xs, stride, c.off, c.w);
#endif
#ifdef DUALNERF_HAVE_AVX2
  int n = 0;
  for (int half = 0; half < 2; ++half) {
    __m256i off[8];
    __m256 w[8];
    n = corners8(t, xs + 8 * half, stride, off, w);
    for (int k = 0; k < n; ++k) {
      _mm256_storeu_si256(reinterpret_cast<__m256i*>(c.off[k] + 8 * half), off[k]);
      _mm256_storeu_ps(c.w[k] + 8 * half, w[k]);
    }
  }
  return n;
#else
  return 0;
#endif
}
#endif

}  // namespace

// Every table's features for points [begin, end) into rows (i - row0) of out_a (and out_b: the second
// field's tables data_b, when given). vector_path: 16 points at a time where the tables allow it.
void dualnerf::lookup_range(const std::vector<Table>& tables, const std::vector<const float*>& data_a,
                  const std::vector<const float*>* data_b, const float* xp, float* out_a, float* out_b,
                  int64_t n_out, int64_t begin, int64_t end, int64_t row0, bool vector_path) {
  auto scalar = [&](size_t k, int64_t from, int64_t to) {
    if (data_b) forward_table_pair<2>(tables[k], data_a[k], (*data_b)[k], xp, out_a, out_b, n_out, from, to, row0);
    else forward_any(tables[k], data_a[k], xp, out_a, n_out, from, to, row0);
  };
  int64_t vector_end = begin;
#ifdef DUALNERF_HAVE_AVX512
  if (vector_path && avx512_available()) {
    vector_end = begin + (end - begin) / kLookupLanes * kLookupLanes;
    const int64_t n = vector_end - begin;
    const std::vector<float> xs = coordinate_arrays(xp, begin, n);
    for (size_t k = 0; k < tables.size(); ++k) {
      if (!vector_lookup_applies(tables[k])) {
        scalar(k, begin, vector_end);
        continue;
      }
      for (int64_t i = 0; i < n; i += kLookupLanes) {
        float* oa = out_a + n_out * (begin + i - row0);
        if (data_b)
          lookup16<true>(tables[k], data_a[k], (*data_b)[k], xs.data() + i, n, oa, out_b + n_out * (begin + i - row0),
                         n_out);
        else
          lookup16<false>(tables[k], data_a[k], nullptr, xs.data() + i, n, oa, nullptr, n_out);
      }
    }
  }
#endif
#ifdef DUALNERF_HAVE_AVX2
  if (vector_path && !avx512_available()) {
    vector_end = begin + (end - begin) / 8 * 8;
    const int64_t n = vector_end - begin;
    const std::vector<float> xs = coordinate_arrays(xp, begin, n);
    for (size_t k = 0; k < tables.size(); ++k) {
      if (!vector_lookup_applies(tables[k])) {
        scalar(k, begin, vector_end);
        continue;
      }
      if (table_cells(tables[k]) * tables[k].stride * 4 > kPrefetchTableBytes)
        prefetch_table8(tables[k], data_a[k], data_b && (*data_b)[k] != data_a[k] + 2 ? (*data_b)[k] : nullptr,
                        xs.data(), n);
      for (int64_t i = 0; i < n; i += 8) {
        float* oa = out_a + n_out * (begin + i - row0);
        if (data_b)
          lookup8<true>(tables[k], data_a[k], (*data_b)[k], xs.data() + i, n, oa, out_b + n_out * (begin + i - row0),
                        n_out);
        else
          lookup8<false>(tables[k], data_a[k], nullptr, xs.data() + i, n, oa, nullptr, n_out);
      }
    }
  }
#endif
  if (vector_end < end)
    for (size_t k = 0; k < tables.size(); ++k) scalar(k, vector_end, end);
}


at::Tensor encode_forward(at::Tensor x, std::vector<at::Tensor> dense, std::vector<at::Tensor> planes,
                          bool vector_path) {
  TORCH_CHECK(x.dim() == 2 && x.size(1) == 3 && x.scalar_type() == at::kFloat, "x must be (M, 3) float32");
  x = x.contiguous();
  const auto tables = describe(dense, planes);
  for (const auto& t : tables)
    TORCH_CHECK(t.channels == 1 || t.channels == 2 || t.channels == 4 || t.channels == 8,
                "grid encoding kernel: features per table must be 1, 2, 4 or 8");
  std::vector<at::Tensor> keep;
  const auto data = table_data(dense, planes, keep);
  const int64_t m = x.size(0), n_out = total_columns(tables);
  auto out = x.new_empty({m, n_out});
  const float* xp = x.data_ptr<float>();
  float* op = out.data_ptr<float>();
  for_each_block(m, [&](int64_t begin, int64_t end) {
    lookup_range(tables, data, nullptr, xp, op, nullptr, n_out, begin, end, 0, vector_path);
  });
  return out;
}

std::vector<at::Tensor> encode_forward_pair(at::Tensor x, std::vector<at::Tensor> dense_a,
                                            std::vector<at::Tensor> planes_a, std::vector<at::Tensor> dense_b,
                                            std::vector<at::Tensor> planes_b, bool vector_path) {
  TORCH_CHECK(x.dim() == 2 && x.size(1) == 3 && x.scalar_type() == at::kFloat, "x must be (M, 3) float32");
  x = x.contiguous();
  const auto tables = describe(dense_a, planes_a);
  const auto tables_b = describe(dense_b, planes_b);
  TORCH_CHECK(tables.size() == tables_b.size(), "the two fields must have the same tables");
  for (size_t k = 0; k < tables.size(); ++k)
    TORCH_CHECK(tables[k].res == tables_b[k].res && tables[k].channels == tables_b[k].channels &&
                    tables[k].channels == 2,
                "the two fields must have the same tables, with 2 features each (pair kernel)");
  std::vector<at::Tensor> keep;
  const auto data_a = table_data(dense_a, planes_a, keep);
  const auto data_b = table_data(dense_b, planes_b, keep);
  const int64_t m = x.size(0), n_out = total_columns(tables);
  auto out_a = x.new_empty({m, n_out});
  auto out_b = x.new_empty({m, n_out});
  const float* xp = x.data_ptr<float>();
  float* oa = out_a.data_ptr<float>();
  float* ob = out_b.data_ptr<float>();
  for_each_block(m, [&](int64_t begin, int64_t end) {
    lookup_range(tables, data_a, &data_b, xp, oa, ob, n_out, begin, end, 0, vector_path);
  });
  return {out_a, out_b};
}


// Adds w * grad_out to every table's gradient: parallel over tables, each accumulated by one thread in
// point order (no races, bit-for-bit repeatable sums). flags[k], where given, marks the touched chunks.
void accumulate_gradients(const std::vector<Table>& tables, const float* xp, const float* gp, int64_t m,
                          int64_t n_out, const std::vector<float*>& grads, const std::vector<uint8_t*>& flags,
                          bool vector_path) {
  // With AVX-512, each group of 16 points gets its corner offsets and weights from corners16 (the scalar
  // corners()'s bits, see lookup16); the additions stay scalar, point by point and corner by corner in
  // the scalar order, so the sums are the same bits.
#if defined(DUALNERF_HAVE_AVX2)
  const bool vec = vector_path;                      // AVX-512 where the CPU has it, else AVX2 (group_corners)
#else
  const bool vec = vector_path && avx512_available();
#endif
  const int64_t n_vec = vec ? m / kLookupLanes * kLookupLanes : 0;
  const std::vector<float> xs = coordinate_arrays(xp, 0, n_vec);
  parallel_for(0, static_cast<int64_t>(tables.size()), 1, [&](int64_t begin, int64_t end) {
    for (int64_t k = begin; k < end; ++k) {
      const Table& t = tables[k];
      float* grad = grads[k];
      uint8_t* touched = flags.empty() ? nullptr : flags[k];
      const int64_t c = t.channels;
      auto add = [&](const float* go, int64_t offset, float w) {
        for (int64_t j = 0; j < c; ++j) grad[offset + j] += w * go[j];
        if (touched != nullptr) touched[offset / kTouchChunk] = 1;
      };
      int64_t i = 0;
#if defined(DUALNERF_HAVE_AVX512) || defined(DUALNERF_HAVE_AVX2)
      if (n_vec > 0 && vector_lookup_applies(t)) {
        // The additions wait on the gradient buffer's cache lines (random rows of tables too large for the
        // caches): group g + kScatterAhead's corners are computed and their lines requested while group g
        // adds. The same corners and additions in the same order: the same bits.
        GroupCorners ring[kRing];
        const int64_t groups = n_vec / kLookupLanes;
        auto prepare = [&](int64_t g) {
          GroupCorners& c = ring[g % kRing];
          c.n = group_corners(t, xs.data() + g * kLookupLanes, n_vec, c);
          prefetch_corners(grad, c, t);
        };
        for (int64_t g = 0; g < std::min(kScatterAhead, groups); ++g) prepare(g);
        for (int64_t g = 0; g < groups; ++g) {
          if (g + kScatterAhead < groups) prepare(g + kScatterAhead);
          const GroupCorners& c = ring[g % kRing];
          for (int64_t lane = 0; lane < kLookupLanes; ++lane) {
            const float* go = gp + n_out * (g * kLookupLanes + lane) + t.column;
            for (int corner = 0; corner < c.n; ++corner) add(go, c.off[corner][lane], c.w[corner][lane]);
          }
        }
        i = n_vec;
      }
#endif
      for (; i < m; ++i) {
        const float* go = gp + n_out * i + t.column;
        corners(t, xp + 3 * i, [&](int64_t offset, float w) { add(go, offset, w); });
      }
    }
  });
}

// What both backward entry points check and read: contiguous points and output gradients, the tables.
struct BackwardInputs {
  at::Tensor x, grad_out;
  std::vector<Table> tables;
  int64_t m, n_out;
  BackwardInputs(const at::Tensor& points, const at::Tensor& grad, const std::vector<at::Tensor>& dense,
                 const std::vector<at::Tensor>& planes)
      : x(points.contiguous()), grad_out(grad.contiguous()), tables(describe(dense, planes)), m(x.size(0)),
        n_out(total_columns(tables)) {
    TORCH_CHECK(grad_out.size(0) == m && grad_out.size(1) == n_out, "grad_out must be (M, total features)");
  }
};

std::vector<at::Tensor> encode_backward(at::Tensor x, at::Tensor grad_out, std::vector<at::Tensor> dense,
                                        std::vector<at::Tensor> planes, bool vector_path) {
  const BackwardInputs in(x, grad_out, dense, planes);
  const auto& tables = in.tables;
  // Gradients in the parameters' own shape, channels-last like the tables (the kernel's write order).
  std::vector<at::Tensor> grads;
  std::vector<float*> data;
  for (auto& g : dense) grads.push_back(g.new_empty({0}).resize_(g.sizes(), at::MemoryFormat::ChannelsLast3d).zero_());
  for (auto& p : planes) grads.push_back(p.new_empty({0}).resize_(p.sizes(), at::MemoryFormat::ChannelsLast).zero_());
  for (auto& g : grads) data.push_back(g.data_ptr<float>());
  accumulate_gradients(tables, in.x.data_ptr<float>(), in.grad_out.data_ptr<float>(), in.m, in.n_out, data, {},
                       vector_path);
  return grads;
}

// The backward of encode_forward into persistent gradient buffers (dualnerf.kernels.TableGradients)
// instead of freshly zero-filled tensors: adds to grads[k] exactly as encode_backward does (a zeroed
// buffer ends up with the same bits) and flags the touched chunks in touched[k].
void encode_backward_into(at::Tensor x, at::Tensor grad_out, std::vector<at::Tensor> dense,
                          std::vector<at::Tensor> planes, std::vector<at::Tensor> grads,
                          std::vector<at::Tensor> touched, bool vector_path) {
  const BackwardInputs in(x, grad_out, dense, planes);
  const auto& tables = in.tables;
  TORCH_CHECK(grads.size() == tables.size() && touched.size() == tables.size(), "one buffer per table expected");
  std::vector<at::Tensor> layout = channels_last(dense, true);
  for (auto& p : channels_last(planes, false)) layout.push_back(p);
  std::vector<float*> data;
  std::vector<uint8_t*> flags;
  for (size_t k = 0; k < tables.size(); ++k) {
    TORCH_CHECK(grads[k].scalar_type() == at::kFloat && grads[k].strides() == layout[k].strides() &&
                    grads[k].sizes() == layout[k].sizes(),
                "gradient buffers must be float32 and laid out like their (channels-last) table");
    TORCH_CHECK(touched[k].scalar_type() == at::kByte && touched[k].is_contiguous() &&
                    touched[k].numel() == (grads[k].numel() + kTouchChunk - 1) / kTouchChunk,
                "touched flags must be uint8, one per ", kTouchChunk, " gradient values");
    data.push_back(grads[k].data_ptr<float>());
    flags.push_back(touched[k].data_ptr<uint8_t>());
  }
  accumulate_gradients(tables, in.x.data_ptr<float>(), in.grad_out.data_ptr<float>(), in.m, in.n_out, data, flags,
                       vector_path);
}


// Zeroes the flagged chunks of a gradient buffer and their flags (a TableGradients reset).
void zero_touched(at::Tensor grad, at::Tensor touched) {
  TORCH_CHECK(grad.scalar_type() == at::kFloat && grad.is_non_overlapping_and_dense() &&
                  touched.scalar_type() == at::kByte && touched.numel() == (grad.numel() + kTouchChunk - 1) / kTouchChunk,
              "zero_touched: a float32 buffer and one uint8 flag per ", kTouchChunk, " values expected");
  float* g = grad.data_ptr<float>();
  uint8_t* flags = touched.data_ptr<uint8_t>();
  const int64_t n = grad.numel();
  for (int64_t c = 0; c < touched.numel(); ++c) {
    if (!flags[c]) continue;
    std::fill(g + c * kTouchChunk, g + std::min(n, (c + 1) * kTouchChunk), 0.0f);
    flags[c] = 0;
  }
}

