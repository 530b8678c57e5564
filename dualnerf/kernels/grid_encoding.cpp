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
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <optional>
#include <vector>

#if defined(__x86_64__) && defined(__GNUC__)
#include <cpuid.h>
#include <immintrin.h>
#include <sys/syscall.h>
#include <unistd.h>
#define DUALNERF_HAVE_AVX512 1   // compiled in with a target attribute; used where the CPU has it
#endif

namespace {

#ifdef DUALNERF_HAVE_AVX512
bool avx512_available() { return __builtin_cpu_supports("avx512f"); }
#else
bool avx512_available() { return false; }
#endif

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

std::vector<Table> describe(const std::vector<torch::Tensor>& dense, const std::vector<torch::Tensor>& planes) {
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

std::vector<torch::Tensor> channels_last(const std::vector<torch::Tensor>& tensors, bool dense) {
  std::vector<torch::Tensor> out;
  for (const auto& t : tensors) {
    TORCH_CHECK(t.scalar_type() == torch::kFloat32 && t.device().is_cpu(), "tables must be float32 CPU tensors");
    out.push_back(t.contiguous(dense ? at::MemoryFormat::ChannelsLast3d : at::MemoryFormat::ChannelsLast));
  }
  return out;
}

int64_t table_cells(const Table& t) { return t.kind == 3 ? t.res * t.res * t.res : t.res * t.res; }

int64_t total_columns(const std::vector<Table>& tables) {
  return tables.empty() ? 0 : tables.back().column + tables.back().channels;
}

// Channels-last copies of the tables (no copy when they are stored so) appended to `keep`, which holds
// them alive while the kernel reads their data pointers.
std::vector<const float*> table_data(const std::vector<torch::Tensor>& dense, const std::vector<torch::Tensor>& planes,
                                     std::vector<torch::Tensor>& keep) {
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
  at::parallel_for(0, (m + kBlock - 1) / kBlock, 1, [&](int64_t block_begin, int64_t block_end) {
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

}  // namespace

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

// One corner (offset vector, weight vector) into the accumulators of one or two tables.
template <bool Pair>
__attribute__((target("avx512f"))) inline void gather_corner(__m512i offset, __m512 w, const float* ta,
                                                             const float* tb, __m512 acc[4]) {
  acc[0] = _mm512_add_ps(acc[0], _mm512_mul_ps(w, _mm512_i32gather_ps(offset, ta, 4)));
  acc[1] = _mm512_add_ps(acc[1], _mm512_mul_ps(w, _mm512_i32gather_ps(offset, ta + 1, 4)));
  if (Pair) {
    acc[2] = _mm512_add_ps(acc[2], _mm512_mul_ps(w, _mm512_i32gather_ps(offset, tb, 4)));
    acc[3] = _mm512_add_ps(acc[3], _mm512_mul_ps(w, _mm512_i32gather_ps(offset, tb + 1, 4)));
  }
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
  _mm512_i32scatter_ps(oa + t.column, rows, acc[0], 4);
  _mm512_i32scatter_ps(oa + t.column + 1, rows, acc[1], 4);
  if (Pair) {
    _mm512_i32scatter_ps(ob + t.column, rows, acc[2], 4);
    _mm512_i32scatter_ps(ob + t.column + 1, rows, acc[3], 4);
  }
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

// Every table's features for points [begin, end) into rows (i - row0) of out_a (and out_b: the second
// field's tables data_b, when given). vector_path: 16 points at a time where the tables allow it.
void lookup_range(const std::vector<Table>& tables, const std::vector<const float*>& data_a,
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
  if (vector_end < end)
    for (size_t k = 0; k < tables.size(); ++k) scalar(k, vector_end, end);
}

}  // namespace

torch::Tensor encode_forward(torch::Tensor x, std::vector<torch::Tensor> dense, std::vector<torch::Tensor> planes,
                             bool vector_path) {
  TORCH_CHECK(x.dim() == 2 && x.size(1) == 3 && x.scalar_type() == torch::kFloat32, "x must be (M, 3) float32");
  x = x.contiguous();
  const auto tables = describe(dense, planes);
  for (const auto& t : tables)
    TORCH_CHECK(t.channels == 1 || t.channels == 2 || t.channels == 4 || t.channels == 8,
                "grid encoding kernel: features per table must be 1, 2, 4 or 8");
  std::vector<torch::Tensor> keep;
  const auto data = table_data(dense, planes, keep);
  const int64_t m = x.size(0), n_out = total_columns(tables);
  auto out = torch::empty({m, n_out}, x.options());
  const float* xp = x.data_ptr<float>();
  float* op = out.data_ptr<float>();
  for_each_block(m, [&](int64_t begin, int64_t end) {
    lookup_range(tables, data, nullptr, xp, op, nullptr, n_out, begin, end, 0, vector_path);
  });
  return out;
}

std::vector<torch::Tensor> encode_forward_pair(torch::Tensor x, std::vector<torch::Tensor> dense_a,
                                               std::vector<torch::Tensor> planes_a, std::vector<torch::Tensor> dense_b,
                                               std::vector<torch::Tensor> planes_b, bool vector_path) {
  TORCH_CHECK(x.dim() == 2 && x.size(1) == 3 && x.scalar_type() == torch::kFloat32, "x must be (M, 3) float32");
  x = x.contiguous();
  const auto tables = describe(dense_a, planes_a);
  const auto tables_b = describe(dense_b, planes_b);
  TORCH_CHECK(tables.size() == tables_b.size(), "the two fields must have the same tables");
  for (size_t k = 0; k < tables.size(); ++k)
    TORCH_CHECK(tables[k].res == tables_b[k].res && tables[k].channels == tables_b[k].channels &&
                    tables[k].channels == 2,
                "the two fields must have the same tables, with 2 features each (pair kernel)");
  std::vector<torch::Tensor> keep;
  const auto data_a = table_data(dense_a, planes_a, keep);
  const auto data_b = table_data(dense_b, planes_b, keep);
  const int64_t m = x.size(0), n_out = total_columns(tables);
  auto out_a = torch::empty({m, n_out}, x.options());
  auto out_b = torch::empty({m, n_out}, x.options());
  const float* xp = x.data_ptr<float>();
  float* oa = out_a.data_ptr<float>();
  float* ob = out_b.data_ptr<float>();
  for_each_block(m, [&](int64_t begin, int64_t end) {
    lookup_range(tables, data_a, &data_b, xp, oa, ob, n_out, begin, end, 0, vector_path);
  });
  return {out_a, out_b};
}

// Chunks of gradient values that encode_backward_into flags as touched (for adam_step_touched). Chunks
// never straddle a corner's features (1, 2, 4 or 8 values at an offset that is a multiple of their count).
constexpr int64_t kTouchChunk = 16;

// Adds w * grad_out to every table's gradient: parallel over tables, each accumulated by one thread in
// point order (no races, bit-for-bit repeatable sums). flags[k], where given, marks the touched chunks.
void accumulate_gradients(const std::vector<Table>& tables, const float* xp, const float* gp, int64_t m,
                          int64_t n_out, const std::vector<float*>& grads, const std::vector<uint8_t*>& flags,
                          bool vector_path) {
  // With AVX-512, each group of 16 points gets its corner offsets and weights from corners16 (the scalar
  // corners()'s bits, see lookup16); the additions stay scalar, point by point and corner by corner in
  // the scalar order, so the sums are the same bits.
  const bool vec = vector_path && avx512_available();
  const int64_t n_vec = vec ? m / kLookupLanes * kLookupLanes : 0;
  const std::vector<float> xs = coordinate_arrays(xp, 0, n_vec);
  at::parallel_for(0, static_cast<int64_t>(tables.size()), 1, [&](int64_t begin, int64_t end) {
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
#ifdef DUALNERF_HAVE_AVX512
      if (n_vec > 0 && vector_lookup_applies(t)) {
        for (; i < n_vec; i += kLookupLanes) {
          int32_t offsets[8][kLookupLanes];
          float weights[8][kLookupLanes];
          const int n = corners16_to_arrays(t, xs.data() + i, n_vec, offsets, weights);
          for (int64_t lane = 0; lane < kLookupLanes; ++lane) {
            const float* go = gp + n_out * (i + lane) + t.column;
            for (int corner = 0; corner < n; ++corner) add(go, offsets[corner][lane], weights[corner][lane]);
          }
        }
      }
#endif
      for (; i < m; ++i) {
        const float* go = gp + n_out * i + t.column;
        corners(t, xp + 3 * i, [&](int64_t offset, float w) { add(go, offset, w); });
      }
    }
  });
}

std::vector<torch::Tensor> encode_backward(torch::Tensor x, torch::Tensor grad_out, std::vector<torch::Tensor> dense,
                                           std::vector<torch::Tensor> planes, bool vector_path) {
  x = x.contiguous();
  grad_out = grad_out.contiguous();
  const auto tables = describe(dense, planes);
  const int64_t m = x.size(0), n_out = total_columns(tables);
  TORCH_CHECK(grad_out.size(0) == m && grad_out.size(1) == n_out, "grad_out must be (M, total features)");
  // Gradients in the parameters' own shape, channels-last like the tables (the kernel's write order).
  std::vector<torch::Tensor> grads;
  std::vector<float*> data;
  for (auto& g : dense) grads.push_back(torch::zeros_like(g, at::MemoryFormat::ChannelsLast3d));
  for (auto& p : planes) grads.push_back(torch::zeros_like(p, at::MemoryFormat::ChannelsLast));
  for (auto& g : grads) data.push_back(g.data_ptr<float>());
  accumulate_gradients(tables, x.data_ptr<float>(), grad_out.data_ptr<float>(), m, n_out, data, {}, vector_path);
  return grads;
}

// The backward of encode_forward into persistent gradient buffers (dualnerf.kernels.TableGradients)
// instead of freshly zero-filled tensors: adds to grads[k] exactly as encode_backward does (a zeroed
// buffer ends up with the same bits) and flags the touched chunks in touched[k].
void encode_backward_into(torch::Tensor x, torch::Tensor grad_out, std::vector<torch::Tensor> dense,
                          std::vector<torch::Tensor> planes, std::vector<torch::Tensor> grads,
                          std::vector<torch::Tensor> touched, bool vector_path) {
  x = x.contiguous();
  grad_out = grad_out.contiguous();
  const auto tables = describe(dense, planes);
  const int64_t m = x.size(0), n_out = total_columns(tables);
  TORCH_CHECK(grad_out.size(0) == m && grad_out.size(1) == n_out, "grad_out must be (M, total features)");
  TORCH_CHECK(grads.size() == tables.size() && touched.size() == tables.size(), "one buffer per table expected");
  std::vector<torch::Tensor> layout = channels_last(dense, true);
  for (auto& p : channels_last(planes, false)) layout.push_back(p);
  std::vector<float*> data;
  std::vector<uint8_t*> flags;
  for (size_t k = 0; k < tables.size(); ++k) {
    TORCH_CHECK(grads[k].scalar_type() == torch::kFloat32 && grads[k].strides() == layout[k].strides() &&
                    grads[k].sizes() == layout[k].sizes(),
                "gradient buffers must be float32 and laid out like their (channels-last) table");
    TORCH_CHECK(touched[k].scalar_type() == torch::kUInt8 && touched[k].is_contiguous() &&
                    touched[k].numel() == (grads[k].numel() + kTouchChunk - 1) / kTouchChunk,
                "touched flags must be uint8, one per ", kTouchChunk, " gradient values");
    data.push_back(grads[k].data_ptr<float>());
    flags.push_back(touched[k].data_ptr<uint8_t>());
  }
  accumulate_gradients(tables, x.data_ptr<float>(), grad_out.data_ptr<float>(), m, n_out, data, flags, vector_path);
}


// Zeroes the flagged chunks of a gradient buffer and their flags (a TableGradients reset).
void zero_touched(torch::Tensor grad, torch::Tensor touched) {
  TORCH_CHECK(grad.scalar_type() == torch::kFloat32 && grad.is_non_overlapping_and_dense() &&
                  touched.scalar_type() == torch::kUInt8 && touched.numel() == (grad.numel() + kTouchChunk - 1) / kTouchChunk,
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

// ---- Inference: look-ups and both MLPs of a field in one pass (renders, no autograd) ----
//
// A render evaluates millions of samples without gradients. Through torch, every MLP layer streams its
// (M, 64) activations through memory several times (bias copy, matmul, ReLU, concatenation, block
// copies: ~40% of a render in the profile). Here a block of kInferBlock samples goes through the
// look-ups and all four layers while it stays in cache, and only (h_sigma, h_color) are written.
//
// A layer is y = b + sum_k x_k W[:, k] (nn.Linear), accumulated as a chain of fused multiply-adds in k
// order starting from the bias, on the AVX-512 path and the portable path alike (std::fma rounds
// exactly like the vector instruction): a sample's result does not depend on the path, its block, its
// neighbours or the thread count. It agrees with torch's matmul to float32 rounding, not bit for bit.

namespace {

constexpr int64_t kInferBlock = 128;
constexpr int kLanes = 16;   // floats per AVX-512 vector; layer widths are padded to a multiple of this

#ifdef DUALNERF_HAVE_AVX512
// The first `left` lanes of a 16-lane vector (all from 16 on, none for left <= 0): masked row tails.
inline __mmask16 first_lanes(int64_t left) {
  return left >= kLanes ? static_cast<__mmask16>(0xFFFF)
                        : static_cast<__mmask16>((1u << (left > 0 ? left : 0)) - 1u);
}
#endif

struct Layer {
  const float* wt;   // (in, out_pad) row-major: W transposed, zero-padded columns
  const float* b;    // (out_pad), zero-padded
  int in, out, out_pad;
};

// Rows [0, rows) of out = relu?(in @ wt + b), portable code.
void layer_rows_portable(const Layer& l, const float* in, int64_t ld_in, int64_t rows, float* out, int64_t ld_out,
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

void layer_rows(const Layer& l, const float* in, int64_t ld_in, int64_t rows, float* out, int64_t ld_out, bool relu,
                bool vector_path) {
#ifdef DUALNERF_HAVE_AVX512
  if (vector_path) {
    switch (l.out_pad / kLanes) {
      case 1: return layer_rows_avx512<1>(l, in, ld_in, rows, out, ld_out, relu);
      case 2: return layer_rows_avx512<2>(l, in, ld_in, rows, out, ld_out, relu);
      case 4: return layer_rows_avx512<4>(l, in, ld_in, rows, out, ld_out, relu);
      case 8: return layer_rows_avx512<8>(l, in, ld_in, rows, out, ld_out, relu);
    }
  }
#endif
  layer_rows_portable(l, in, ld_in, rows, out, ld_out, relu);
}

// ---- bfloat16 MLPs (field_inference(..., bf16=true)): for renders that tolerate bf16 rounding ----
//
// Each layer's inputs and weights are rounded to bfloat16 (round to nearest even), the products summed in
// float32, the bias added in float32. Products of two bf16 values are exact in float32, so the AMX tile
// path (TDPBF16PS) and the emulation (rounded values through the float32 layer code) differ only in the
// order of the float32 sums. The emulation runs where the CPU has no AMX; both are compared with the
// float32 path in tests/test_inference_kernel.py.
inline float round_bf16(float x) {
  uint32_t u;
  std::memcpy(&u, &x, sizeof u);
  if ((u & 0x7f800000u) != 0x7f800000u) u = (u + 0x7fffu + ((u >> 16) & 1u)) & 0xffff0000u;   // inf, NaN: as is
  std::memcpy(&x, &u, sizeof x);
  return x;
}

constexpr int kTile = 16;      // AMX tile: 16 rows of 64 bytes (16 floats, or 32 bf16 = 16 bf16 pairs)
constexpr int kTileK = 32;     // bf16 inputs per tile row
constexpr int kMaxColumnTiles = 4;   // sum tiles per row tile: layers up to 64 outputs run on tiles

struct Bf16Layers {
  std::vector<float> rounded[4];     // wt rounded to bf16 values (the emulation's weights)
  std::vector<uint16_t> packed[4];   // AMX layout: (k tile, column tile, 16 input pairs, 16 columns, 2) bf16
  std::vector<float> bias_rows[4];   // AMX: the bias on 16 rows (the sums' starting tile)
  int k_pad[4];                      // inputs rounded up to a multiple of kTileK
};

bool amx_available() {
#ifdef DUALNERF_HAVE_AVX512
  static const bool available = [] {
    unsigned eax = 0, ebx = 0, ecx = 0, edx = 0;
    if (!__builtin_cpu_supports("avx512f") || !__builtin_cpu_supports("avx512bf16") ||
        !__get_cpuid_count(7, 0, &eax, &ebx, &ecx, &edx))
      return false;
    if (!(edx & (1u << 22)) || !(edx & (1u << 24))) return false;   // AMX-BF16, AMX-TILE
    // Linux grants a process the tile registers' state only on request (ARCH_REQ_XCOMP_PERM, XTILEDATA).
    return syscall(SYS_arch_prctl, 0x1023, 18) == 0;
  }();
  return available;
#else
  return false;
#endif
}

// A field's density MLP (features -> hidden -> [h_sigma, geo]) and colour MLP ([geo, sh] -> hidden -> rgb).
// bf16 set: the layers run in bfloat16 (AMX tiles when amx, else the emulation).
struct FieldMlps {
  Layer layer[4];
  int n_sh;
  const Bf16Layers* bf16 = nullptr;
  bool amx = false;
};

Bf16Layers bf16_layers(const FieldMlps& m) {
  Bf16Layers out;
  for (int i = 0; i < 4; ++i) {
    const Layer& l = m.layer[i];
    const int64_t size = static_cast<int64_t>(l.in) * l.out_pad;
    out.rounded[i].resize(size);
    for (int64_t j = 0; j < size; ++j) out.rounded[i][j] = round_bf16(l.wt[j]);
    const int k_pad = (l.in + kTileK - 1) / kTileK * kTileK, n_tiles = l.out_pad / kTile;
    out.k_pad[i] = k_pad;
    out.bias_rows[i].resize(static_cast<size_t>(kTile) * l.out_pad);
    for (int r = 0; r < kTile; ++r) std::copy(l.b, l.b + l.out_pad, out.bias_rows[i].begin() + r * l.out_pad);
    out.packed[i].assign(static_cast<size_t>(k_pad) * l.out_pad, 0);
    for (int k = 0; k < l.in; ++k)
      for (int col = 0; col < l.out_pad; ++col) {
        const int kt = k / kTileK, pair = (k % kTileK) / 2, nt = col / kTile;
        const size_t at = ((static_cast<size_t>(kt) * n_tiles + nt) * kTile + pair) * (2 * kTile) +
                          2 * (col % kTile) + (k % 2);
        uint32_t bits;
        std::memcpy(&bits, &out.rounded[i][static_cast<int64_t>(k) * l.out_pad + col], sizeof bits);
        out.packed[i][at] = static_cast<uint16_t>(bits >> 16);
      }
  }
  return out;
}

#ifdef DUALNERF_HAVE_AVX512
struct alignas(64) TileConfig {
  uint8_t palette, start_row, reserved[14];
  uint16_t colsb[16];
  uint8_t rows[16];
};

// Tiles 0-3: sums (16 rows x 16 floats) for up to 4 column tiles (64 outputs); 4: inputs (16 rows x 32
// bf16); 5: weights (16 input pairs x 16 columns x 2).

__attribute__((target("amx-tile"))) void amx_begin() {
  TileConfig config{};
  config.palette = 1;
  for (int t = 0; t < 6; ++t) {
    config.colsb[t] = 64;
    config.rows[t] = kTile;
  }
  // GCC's _tile_loadconfig tells the compiler it reads 8 bytes only; without this barrier the stores to
  // colsb and rows are dropped as dead and ldtilecfg faults on the incomplete configuration.
  asm volatile("" : : "r"(&config) : "memory");
  _tile_loadconfig(&config);
}

__attribute__((target("amx-tile"))) void amx_end() { _tile_release(); }

// Rows [0, rows <= kInferBlock) of out = bf16(relu?(in)) @ bf16(W) + b on AMX tiles (amx_begin first).
// The ReLU applies to the inputs: the previous layer's tile stores are read once, by this conversion
// (reading tile-stored rows back right away for a ReLU pass cost 15% of a render).
// out must have room for the rows rounded up to 16 and all out_pad columns (scratch rows and padding
// columns are written too); bias_rows: the bias repeated on 16 rows, the sums' starting value.
// a: scratch for kInferBlock x k_pad bf16 inputs.
__attribute__((target("amx-tile,amx-bf16,avx512f,avx512bf16"))) void layer_rows_amx(
    const Layer& l, const uint16_t* packed, const float* bias_rows, int k_pad, const float* in, int64_t ld_in,
    int64_t rows, float* out, int64_t ld_out, bool relu_inputs, uint16_t* a) {
  const int64_t padded_rows = (rows + kTile - 1) / kTile * kTile;
  const __m512 zero = _mm512_setzero_ps();
  for (int64_t r = 0; r < padded_rows; ++r)
    for (int k = 0; k < k_pad; k += kTile) {
      const int left = r < rows ? l.in - k : 0;
      const __mmask16 mask = first_lanes(left);
      __m512 x = _mm512_maskz_loadu_ps(mask, in + r * ld_in + k);
      if (relu_inputs) x = _mm512_max_ps(x, zero);
      _mm256_storeu_si256(reinterpret_cast<__m256i*>(a + r * k_pad + k), (__m256i)_mm512_cvtneps_pbh(x));
    }
  const int n_tiles = l.out_pad / kTile, k_tiles = k_pad / kTileK;
  const int64_t ld_bytes = 4 * ld_out, bias_bytes = 4 * l.out_pad;
  const size_t b_tile = static_cast<size_t>(kTile) * 2 * kTile;
  for (int64_t rt = 0; rt < padded_rows; rt += kTile) {
    float* o = out + rt * ld_out;
    // Tile numbers are immediates: one branch per column-tile count.
    _tile_loadd(0, bias_rows, bias_bytes);
    if (n_tiles > 1) _tile_loadd(1, bias_rows + kTile, bias_bytes);
    if (n_tiles > 2) _tile_loadd(2, bias_rows + 2 * kTile, bias_bytes);
    if (n_tiles > 3) _tile_loadd(3, bias_rows + 3 * kTile, bias_bytes);
    for (int kt = 0; kt < k_tiles; ++kt) {
      _tile_loadd(4, a + rt * k_pad + kt * kTileK, 2 * k_pad);
      const uint16_t* w = packed + static_cast<size_t>(kt) * n_tiles * b_tile;
      _tile_loadd(5, w, 4 * kTile);
      _tile_dpbf16ps(0, 4, 5);
      if (n_tiles > 1) {
        _tile_loadd(5, w + b_tile, 4 * kTile);
        _tile_dpbf16ps(1, 4, 5);
      }
      if (n_tiles > 2) {
        _tile_loadd(5, w + 2 * b_tile, 4 * kTile);
        _tile_dpbf16ps(2, 4, 5);
      }
      if (n_tiles > 3) {
        _tile_loadd(5, w + 3 * b_tile, 4 * kTile);
        _tile_dpbf16ps(3, 4, 5);
      }
    }
    _tile_stored(0, o, ld_bytes);
    if (n_tiles > 1) _tile_stored(1, o + kTile, ld_bytes);
    if (n_tiles > 2) _tile_stored(2, o + 2 * kTile, ld_bytes);
    if (n_tiles > 3) _tile_stored(3, o + 3 * kTile, ld_bytes);
  }
}
#endif

FieldMlps describe_mlps(const std::vector<torch::Tensor>& t, int64_t n_features, int64_t n_sh) {
  TORCH_CHECK(t.size() == 8, "field_inference: 8 MLP tensors expected (wt, b for 4 layers)");
  FieldMlps m;
  const int64_t outs[4] = {-1, -1, -1, 3};
  for (int i = 0; i < 4; ++i) {
    const auto& wt = t[2 * i];
    const auto& b = t[2 * i + 1];
    TORCH_CHECK(wt.dim() == 2 && wt.is_contiguous() && wt.scalar_type() == torch::kFloat32 && b.dim() == 1 &&
                    b.is_contiguous() && b.size(0) == wt.size(1) && wt.size(1) % kLanes == 0,
                "field_inference: layer weights must be contiguous float32 (in, out padded to 16) with a bias");
    m.layer[i] = {wt.data_ptr<float>(), b.data_ptr<float>(), static_cast<int>(wt.size(0)),
                  static_cast<int>(outs[i] > 0 ? outs[i] : wt.size(1)), static_cast<int>(wt.size(1))};
  }
  m.layer[0].out = m.layer[1].in;           // hidden width
  m.layer[2].out = m.layer[3].in;
  m.layer[1].out = m.layer[2].in - static_cast<int>(n_sh) + 1;   // 1 + geo features
  m.n_sh = static_cast<int>(n_sh);
  TORCH_CHECK(m.layer[0].in == n_features, "field_inference: first layer takes ", m.layer[0].in,
              " features, the tables give ", n_features);
  TORCH_CHECK(m.layer[1].out >= 1 && m.layer[1].out <= m.layer[1].out_pad && m.layer[0].out <= m.layer[0].out_pad &&
                  m.layer[2].out <= m.layer[2].out_pad,
              "field_inference: inconsistent MLP shapes");
  return m;
}

struct Scratch {
  std::vector<float> hidden, density_out, color_in, rgb, rounded_in;
  std::vector<uint16_t> tile_a;
  explicit Scratch(const FieldMlps& m)
      : hidden(kInferBlock * std::max(m.layer[0].out_pad, m.layer[2].out_pad)),
        density_out(kInferBlock * m.layer[1].out_pad), color_in(kInferBlock * m.layer[2].in),
        rgb(kInferBlock * m.layer[3].out_pad) {
    if (!m.bf16) return;
    int widest = 0, widest_pad = 0;
    for (int i = 0; i < 4; ++i) {
      widest = std::max(widest, m.layer[i].in);
      widest_pad = std::max(widest_pad, m.bf16->k_pad[i]);
    }
    rounded_in.resize(kInferBlock * widest);
    tile_a.resize(kInferBlock * widest_pad);
  }
};

// Layer i of m on rows [0, rows) in m's precision (float32, or bf16 on AMX tiles or emulated). On tiles,
// the hidden layers' ReLU is left to the next layer's input conversion: only layers 1 and 3 read them.
void apply_layer(const FieldMlps& m, int i, const float* in, int64_t ld_in, int64_t rows, float* out, int64_t ld_out,
                 bool relu, Scratch& s, bool vector_path) {
  const Layer& l = m.layer[i];
  if (!m.bf16) return layer_rows(l, in, ld_in, rows, out, ld_out, relu, vector_path);
#ifdef DUALNERF_HAVE_AVX512
  if (m.amx)
    return layer_rows_amx(l, m.bf16->packed[i].data(), m.bf16->bias_rows[i].data(), m.bf16->k_pad[i], in, ld_in,
                          rows, out, ld_out, i == 1 || i == 3, s.tile_a.data());
#endif
  float* x = s.rounded_in.data();
  for (int64_t r = 0; r < rows; ++r)
    for (int k = 0; k < l.in; ++k) x[r * l.in + k] = round_bf16(in[r * ld_in + k]);
  Layer rounded = l;
  rounded.wt = m.bf16->rounded[i].data();
  layer_rows(rounded, x, l.in, rows, out, ld_out, relu, vector_path);
}

// (h_sigma, h_color) of `rows` samples from their features and direction SH features: row r's are
// sh + r * n_sh, or sh + sh_index[r] * n_sh with an index (a render's per-ray features).
void field_mlps(const FieldMlps& m, const float* features, int64_t ld_features, const float* sh,
                const int64_t* sh_index, int64_t rows, Scratch& s, float* h_sigma, float* h_color, bool vector_path) {
  const Layer* l = m.layer;
  const int64_t ld_h = std::max(l[0].out_pad, l[2].out_pad), ld_d = l[1].out_pad, ld_c = l[2].in;
  apply_layer(m, 0, features, ld_features, rows, s.hidden.data(), ld_h, true, s, vector_path);
  apply_layer(m, 1, s.hidden.data(), ld_h, rows, s.density_out.data(), ld_d, false, s, vector_path);
  const int geo = l[1].out - 1;
  for (int64_t r = 0; r < rows; ++r) {
    float* c = s.color_in.data() + r * ld_c;
    const float* d = s.density_out.data() + r * ld_d;
    h_sigma[r] = d[0];
    std::copy(d + 1, d + 1 + geo, c);
    const float* sh_row = sh + (sh_index ? sh_index[r] : r) * m.n_sh;
    std::copy(sh_row, sh_row + m.n_sh, c + geo);
  }
  apply_layer(m, 2, s.color_in.data(), ld_c, rows, s.hidden.data(), ld_h, true, s, vector_path);
  apply_layer(m, 3, s.hidden.data(), ld_h, rows, s.rgb.data(), l[3].out_pad, false, s, vector_path);
  for (int64_t r = 0; r < rows; ++r)
    for (int j = 0; j < 3; ++j) h_color[3 * r + j] = s.rgb[r * l[3].out_pad + j];
}

}  // namespace

// One field (dense_b empty) or the dual field: h = (1 - w) h_S + w h_D per output (eqs. 4-5), with
// a = f_S and b = f_D. Returns (h_sigma (M,), h_color (M, 3)).
std::vector<torch::Tensor> field_inference(torch::Tensor x, torch::Tensor sh, std::vector<torch::Tensor> dense_a,
                                           std::vector<torch::Tensor> planes_a, std::vector<torch::Tensor> mlp_a,
                                           std::vector<torch::Tensor> dense_b, std::vector<torch::Tensor> planes_b,
                                           std::vector<torch::Tensor> mlp_b, double w_density, double w_color,
                                           std::vector<torch::Tensor> interleaved, std::optional<torch::Tensor> sh_index,
                                           bool vector_path, bool bf16, bool amx) {
  TORCH_CHECK(x.dim() == 2 && x.size(1) == 3 && x.scalar_type() == torch::kFloat32, "x must be (M, 3) float32");
  const bool indexed = sh_index.has_value();
  TORCH_CHECK(sh.dim() == 2 && (indexed || sh.size(0) == x.size(0)) && sh.scalar_type() == torch::kFloat32,
              "sh must be (M, S) float32, or (R, S) with sh_index");
  x = x.contiguous();
  sh = sh.contiguous();
  torch::Tensor sh_rows_index;
  if (indexed) {           // sample i's direction features are sh[sh_index[i]] (one row per ray)
    sh_rows_index = sh_index->contiguous();
    TORCH_CHECK(sh_rows_index.dim() == 1 && sh_rows_index.size(0) == x.size(0) &&
                    sh_rows_index.scalar_type() == torch::kInt64,
                "sh_index must be (M,) int64");
    if (x.size(0) > 0)
      TORCH_CHECK(sh_rows_index.min().item<int64_t>() >= 0 && sh_rows_index.max().item<int64_t>() < sh.size(0),
                  "sh_index out of range of sh's rows");
  }
  const int64_t* index = indexed ? sh_rows_index.data_ptr<int64_t>() : nullptr;
  const bool dual = !dense_b.empty();
  auto tables = describe(dense_a, planes_a);
  for (const auto& t : tables)
    TORCH_CHECK(t.channels == 2, "field_inference: the fused inference path needs 2 features per table");
  if (dual) {
    const auto tables_b = describe(dense_b, planes_b);
    TORCH_CHECK(tables.size() == tables_b.size(), "the two fields must have the same tables");
    for (size_t k = 0; k < tables.size(); ++k)
      TORCH_CHECK(tables[k].res == tables_b[k].res && tables_b[k].channels == 2, "the two fields must have the same tables");
  }
  std::vector<torch::Tensor> keep;
  std::vector<const float*> data_a, data_b;
  if (dual && !interleaved.empty()) {        // interleave_pair's tables: f_S's features at +0, f_D's at +2
    TORCH_CHECK(interleaved.size() == tables.size(), "field_inference: one interleaved table per table expected");
    for (size_t k = 0; k < tables.size(); ++k) {
      TORCH_CHECK(interleaved[k].is_contiguous() && interleaved[k].scalar_type() == torch::kFloat32 &&
                      interleaved[k].numel() == 4 * table_cells(tables[k]),
                  "field_inference: interleaved tables must come from interleave_pair for these tables");
      tables[k].stride = 4;
      data_a.push_back(interleaved[k].data_ptr<float>());
      data_b.push_back(interleaved[k].data_ptr<float>() + 2);
    }
  } else {
    data_a = table_data(dense_a, planes_a, keep);
    if (dual) data_b = table_data(dense_b, planes_b, keep);
  }
  const int64_t m = x.size(0), n_features = total_columns(tables), n_sh = sh.size(1);
  FieldMlps mlps_a = describe_mlps(mlp_a, n_features, n_sh);
  FieldMlps mlps_b = dual ? describe_mlps(mlp_b, n_features, n_sh) : mlps_a;
  if (dual)
    for (int i = 0; i < 4; ++i)
      TORCH_CHECK(mlps_b.layer[i].in == mlps_a.layer[i].in && mlps_b.layer[i].out_pad == mlps_a.layer[i].out_pad,
                  "the two fields must have the same MLP shapes");
  auto h_sigma = torch::empty({m}, x.options());
  auto h_color = torch::empty({m, 3}, x.options());
  const float *xp = x.data_ptr<float>(), *shp = sh.data_ptr<float>();
  float *sp = h_sigma.data_ptr<float>(), *cp = h_color.data_ptr<float>();
  // The coefficients rounded to float as torch rounds a Python scalar: (1 - w) in double first.
  const float wd = static_cast<float>(w_density), wc = static_cast<float>(w_color);
  const float keep_d = static_cast<float>(1.0 - w_density), keep_c = static_cast<float>(1.0 - w_color);
  const bool vec = vector_path && avx512_available();
  bool widths_fit = true;      // the tile code holds up to kMaxColumnTiles x 16 outputs per layer
  for (int i = 0; i < 4; ++i) widths_fit = widths_fit && mlps_a.layer[i].out_pad <= kMaxColumnTiles * kTile;
  const bool tiles = bf16 && amx && vec && widths_fit && amx_available();
  Bf16Layers bf16_a, bf16_b;
  if (bf16) {
    bf16_a = bf16_layers(mlps_a);
    mlps_a.bf16 = &bf16_a;
    mlps_a.amx = tiles;
    if (dual) {
      bf16_b = bf16_layers(mlps_b);
      mlps_b.bf16 = &bf16_b;
      mlps_b.amx = tiles;
    }
  }
  const int64_t n_blocks = (m + kInferBlock - 1) / kInferBlock;
  at::parallel_for(0, n_blocks, 1, [&](int64_t block_begin, int64_t block_end) {
#ifdef DUALNERF_HAVE_AVX512
    if (tiles) amx_begin();     // the tile configuration is per thread
#endif
    Scratch scratch(mlps_a);
    std::vector<float> feat_a(kInferBlock * n_features), feat_b(dual ? kInferBlock * n_features : 0);
    std::vector<float> sigma_b(dual ? kInferBlock : 0), color_b(dual ? 3 * kInferBlock : 0);
    for (int64_t blk = block_begin; blk < block_end; ++blk) {
      const int64_t begin = blk * kInferBlock, end = std::min(m, begin + kInferBlock), rows = end - begin;
      lookup_range(tables, data_a, dual ? &data_b : nullptr, xp, feat_a.data(), feat_b.data(), n_features, begin,
                   end, begin, vector_path);
      float* sig = sp + begin;
      float* col = cp + 3 * begin;
      const float* sh_rows = index ? shp : shp + begin * n_sh;
      const int64_t* sh_index_rows = index ? index + begin : nullptr;
      field_mlps(mlps_a, feat_a.data(), n_features, sh_rows, sh_index_rows, rows, scratch, sig, col, vec);
      if (!dual) continue;
      field_mlps(mlps_b, feat_b.data(), n_features, sh_rows, sh_index_rows, rows, scratch, sigma_b.data(),
                 color_b.data(), vec);
      // Eqs. 4-5 in the order of dualnerf.dual_field._fuse: (1 - w) * h_S + w * h_D.
      for (int64_t r = 0; r < rows; ++r) sig[r] = keep_d * sig[r] + wd * sigma_b[r];
      for (int64_t r = 0; r < 3 * rows; ++r) col[r] = keep_c * col[r] + wc * color_b[r];
    }
#ifdef DUALNERF_HAVE_AVX512
    if (tiles) amx_end();
#endif
  });
  return {h_sigma, h_color};
}

// The two fields' tables of a dual field in one (cells, 4) table each: (f_S's 2 features, f_D's 2) per
// cell. field_inference then reads both fields' corner from one cache line instead of two (the look-ups
// of a render are bound by the cache misses); the values and the arithmetic are the same, so the
// results are too, bit for bit. A render builds them once per image (~100 MB at the default sizes).
std::vector<torch::Tensor> interleave_pair(std::vector<torch::Tensor> dense_a, std::vector<torch::Tensor> planes_a,
                                           std::vector<torch::Tensor> dense_b, std::vector<torch::Tensor> planes_b) {
  const auto tables = describe(dense_a, planes_a);
  const auto tables_b = describe(dense_b, planes_b);
  TORCH_CHECK(tables.size() == tables_b.size(), "the two fields must have the same tables");
  for (size_t k = 0; k < tables.size(); ++k)
    TORCH_CHECK(tables[k].res == tables_b[k].res && tables[k].channels == 2 && tables_b[k].channels == 2,
                "interleave_pair: the two fields must have the same tables, with 2 features each");
  std::vector<torch::Tensor> keep;
  const auto data_a = table_data(dense_a, planes_a, keep);
  const auto data_b = table_data(dense_b, planes_b, keep);
  std::vector<torch::Tensor> out;
  for (size_t k = 0; k < tables.size(); ++k) {
    const int64_t cells = table_cells(tables[k]);
    auto pair = torch::empty({4 * cells}, torch::kFloat32);
    float* o = pair.data_ptr<float>();
    const float *a = data_a[k], *b = data_b[k];
    at::parallel_for(0, cells, 4096, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i) {
        o[4 * i] = a[2 * i];
        o[4 * i + 1] = a[2 * i + 1];
        o[4 * i + 2] = b[2 * i];
        o[4 * i + 3] = b[2 * i + 1];
      }
    });
    out.push_back(pair);
  }
  return out;
}

// The MLPs alone on given features (the frozen f_S in a dual-field training step, whose look-ups the
// pair kernel already did): (h_sigma (M,), h_color (M, 3)), as field_inference computes them.
std::vector<torch::Tensor> mlp_inference(torch::Tensor features, torch::Tensor sh, std::vector<torch::Tensor> mlp,
                                         bool vector_path) {
  TORCH_CHECK(features.dim() == 2 && features.scalar_type() == torch::kFloat32 && sh.dim() == 2 &&
                  sh.size(0) == features.size(0) && sh.scalar_type() == torch::kFloat32,
              "mlp_inference: (M, F) features and (M, S) sh, float32");
  features = features.contiguous();
  sh = sh.contiguous();
  const int64_t m = features.size(0), n_features = features.size(1), n_sh = sh.size(1);
  const FieldMlps mlps = describe_mlps(mlp, n_features, n_sh);
  auto h_sigma = torch::empty({m}, features.options());
  auto h_color = torch::empty({m, 3}, features.options());
  const float *fp = features.data_ptr<float>(), *shp = sh.data_ptr<float>();
  float *sp = h_sigma.data_ptr<float>(), *cp = h_color.data_ptr<float>();
  const bool vec = vector_path && avx512_available();
  at::parallel_for(0, (m + kInferBlock - 1) / kInferBlock, 1, [&](int64_t block_begin, int64_t block_end) {
    Scratch scratch(mlps);
    for (int64_t blk = block_begin; blk < block_end; ++blk) {
      const int64_t begin = blk * kInferBlock, rows = std::min(m, begin + kInferBlock) - begin;
      field_mlps(mlps, fp + begin * n_features, n_features, shp + begin * n_sh, nullptr, rows, scratch, sp + begin,
                 cp + 3 * begin, vec);
    }
  });
  return {h_sigma, h_color};
}

bool vector_path_available() { return avx512_available(); }

bool amx_path_available() { return avx512_available() && amx_available(); }




// ---- Adam for the trainer (dualnerf.optim): one pass per tensor, optionally skipping zero gradients ----
//
// The same rounded float operations, in the same order, as dualnerf.optim.adam_reference (built with
// -ffp-contract=off, so no fused multiply-adds), hence bit-for-bit its result:
//   m = b1 m + (1 - b1) g;  v = b2 v + (1 - b2) g g;  p = p - step_size (m / (sqrt(v) / bc2_sqrt + eps)).
// skip_zero: entries whose gradient is exactly 0 keep p, m and v (instant-NGP's rule for feature tables:
// a batch touches a small part of a table, and the dense update of every entry was memory-bound).
void check_adam_tensors(const torch::Tensor& param, const torch::Tensor& grad, const torch::Tensor& exp_avg,
                        const torch::Tensor& exp_avg_sq) {
  for (const auto* t : {&param, &grad, &exp_avg, &exp_avg_sq})
    TORCH_CHECK(t->scalar_type() == torch::kFloat32 && t->device().is_cpu() && t->numel() == param.numel(),
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

void adam_step(torch::Tensor param, torch::Tensor grad, torch::Tensor exp_avg, torch::Tensor exp_avg_sq, double beta1,
               double beta2, double step_size, double bias_correction2_sqrt, double eps, bool skip_zero) {
  check_adam_tensors(param, grad, exp_avg, exp_avg_sq);
  const AdamUpdate update(beta1, beta2, step_size, bias_correction2_sqrt, eps);
  float* p = param.data_ptr<float>();
  const float* g = grad.data_ptr<float>();
  float* m = exp_avg.data_ptr<float>();
  float* v = exp_avg_sq.data_ptr<float>();
  at::parallel_for(0, param.numel(), 1 << 16, [&](int64_t begin, int64_t end) {
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

// adam_step with skip_zero on the touched chunks of a TableGradients buffer only (an untouched chunk's
// gradients are all zero, so skip_zero would leave it as it is anyway: the same bits as adam_step), then
// zeroes those gradients and flags for the next backward.
void adam_step_touched(torch::Tensor param, torch::Tensor grad, torch::Tensor touched, torch::Tensor exp_avg,
                       torch::Tensor exp_avg_sq, double beta1, double beta2, double step_size,
                       double bias_correction2_sqrt, double eps) {
  check_adam_tensors(param, grad, exp_avg, exp_avg_sq);
  const int64_t n = param.numel();
  TORCH_CHECK(touched.scalar_type() == torch::kUInt8 && touched.is_contiguous() &&
                  touched.numel() == (n + kTouchChunk - 1) / kTouchChunk,
              "adam_step_touched: one uint8 flag per ", kTouchChunk, " values expected");
  const AdamUpdate update(beta1, beta2, step_size, bias_correction2_sqrt, eps);
  float* p = param.data_ptr<float>();
  float* g = grad.data_ptr<float>();
  float* m = exp_avg.data_ptr<float>();
  float* v = exp_avg_sq.data_ptr<float>();
  uint8_t* flags = touched.data_ptr<uint8_t>();
  const bool vec = avx512_available();
  at::parallel_for(0, touched.numel(), 1 << 12, [&](int64_t chunk_begin, int64_t chunk_end) {
    for (int64_t c = chunk_begin; c < chunk_end; ++c) {
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


// ---- The render sampler (dualnerf.rendering.ray_samples): proposal intervals + occupancy test per ray ----
//
// Per ray, in cache: the proposal (the occupancy grid's scaled density at n_proposal bin centres,
// composited), its pdf mixed with the uniform share, inverse-transform sampling of the interval edges at
// the quantiles (i - 0.5 + jitter_i) / S (a merge walk: the quantiles are increasing), and the
// occupancy mask at the interval midpoints. On AVX-512 the proposal runs for 16 rays at once, one per
// lane (its exp and sequential sums were 70% of a render's sampler). The same formulas as proposal_intervals and
// OccupancyGrid.occupied in torch, which stay the reference; they agree to float32 rounding (exp and
// the sums round differently), and the cells of given points are bit-for-bit the reference's.
inline int64_t grid_cell(const float* o, const float* d, float t, float half_r, float top, int64_t r) {
  int64_t cell[3];
  for (int a = 0; a < 3; ++a) {
    const float x = o[a] + t * d[a];
    const float c = (x + 1.0f) * half_r;
    cell[a] = static_cast<int64_t>(std::min(c > 0.0f ? c : 0.0f, top));
  }
  return (cell[0] * r + cell[1]) * r + cell[2];
}

#ifdef DUALNERF_HAVE_AVX512
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
      const float survive = std::exp(-tau);
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
// float operations except the exp (exp16, within a few ulp of std::exp).
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

std::vector<torch::Tensor> ray_samples(torch::Tensor origins, torch::Tensor dirs, torch::Tensor t_start,
                                       torch::Tensor t_end, torch::Tensor density, torch::Tensor mask, double scale,
                                       int64_t n_proposal, int64_t n_samples, double uniform_share,
                                       torch::Tensor jitter, bool vector_path) {
  for (const auto* x : {&origins, &dirs, &t_start, &t_end, &density})
    TORCH_CHECK(x->scalar_type() == torch::kFloat32 && x->device().is_cpu(), "ray_samples: float32 CPU tensors expected");
  TORCH_CHECK(mask.scalar_type() == torch::kBool && mask.sizes() == density.sizes(), "ray_samples: bool mask like density");
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
    TORCH_CHECK(jitter.scalar_type() == torch::kFloat32 && jitter.size(0) == n_rays && jitter.size(1) == S - 1,
                "ray_samples: jitter must be (rays, samples - 1) float32");
  }
  auto t = torch::empty({n_rays, S}, t_start.options());
  auto delta = torch::empty({n_rays, S}, t_start.options());
  auto occupied = torch::empty({n_rays, S}, mask.options());
  const SamplerInputs in{origins.data_ptr<float>(), dirs.data_ptr<float>(), t_start.data_ptr<float>(),
                         t_end.data_ptr<float>(), density.data_ptr<float>(),
                         jittered ? jitter.data_ptr<float>() : nullptr, mask.data_ptr<bool>(), r, P, S,
                         0.5f * static_cast<float>(r), static_cast<float>(r - 1), static_cast<float>(scale),
                         static_cast<float>(1.0 - uniform_share),
                         static_cast<float>(uniform_share / static_cast<double>(P)), t.data_ptr<float>(),
                         delta.data_ptr<float>(), occupied.data_ptr<bool>()};
  // 16 rays at a time on AVX-512 (one per lane; the grid's cells fit int32 there).
  const bool vec = vector_path && avx512_available() && r * r * r < (int64_t(1) << 31);
  at::parallel_for(0, n_rays, 16, [&](int64_t begin, int64_t end) {
    std::vector<float> pdf(16 * P), cdf(16 * (P + 1)), edges(S + 1);
    int64_t i = begin;
#ifdef DUALNERF_HAVE_AVX512
    if (vec)
      for (; i + 16 <= end; i += 16) {
        proposal_avx512(in, i, pdf.data(), cdf.data());
        for (int l = 0; l < 16; ++l) place_samples(in, i + l, pdf.data() + l, cdf.data() + l, 16, edges.data());
      }
#endif
    for (; i < end; ++i) {
      proposal_scalar(in, i, pdf.data(), cdf.data(), 1);
      place_samples(in, i, pdf.data(), cdf.data(), 1, edges.data());
    }
  });
  return {t, delta, occupied};
}

// ---- A render's packing and compositing (dualnerf.rendering.render_rays without autograd) ----
//
// occupied_samples: the occupied samples' points x = o + t d (the same float operations as the torch
// code, so the same bits), their flat index r * S + s in increasing order, their ray, and each ray's first
// entry (R + 1 offsets). composite_rays: the colour and opacity of each ray from its evaluated samples,
// the formulas of rendering.composite with decode_density / decode_color, summed per ray in sample order;
// torch's vectorised exp and sums round differently, so the two agree to float32 rounding
// (tests/test_render_kernels.py).
std::vector<torch::Tensor> occupied_samples(torch::Tensor origins, torch::Tensor dirs, torch::Tensor t,
                                            torch::Tensor mask) {
  for (const auto* x : {&origins, &dirs, &t})
    TORCH_CHECK(x->scalar_type() == torch::kFloat32 && x->device().is_cpu(), "occupied_samples: float32 CPU tensors");
  TORCH_CHECK(mask.scalar_type() == torch::kBool && mask.sizes() == t.sizes() && t.dim() == 2 &&
                  origins.size(0) == t.size(0) && dirs.sizes() == origins.sizes() && origins.size(1) == 3,
              "occupied_samples: origins, dirs (R, 3), t and mask (R, S)");
  origins = origins.contiguous();
  dirs = dirs.contiguous();
  t = t.contiguous();
  mask = mask.contiguous();
  const int64_t n_rays = t.size(0), S = t.size(1);
  auto starts = torch::empty({n_rays + 1}, torch::kInt64);
  int64_t* st = starts.data_ptr<int64_t>();
  const bool* mp = mask.data_ptr<bool>();
  st[0] = 0;
  for (int64_t r = 0; r < n_rays; ++r) {
    int64_t count = 0;
    for (int64_t s = 0; s < S; ++s) count += mp[r * S + s];
    st[r + 1] = st[r] + count;
  }
  const int64_t m = st[n_rays];
  auto x = torch::empty({m, 3}, t.options());
  auto flat = torch::empty({m}, torch::kInt64);
  auto ray = torch::empty({m}, torch::kInt64);
  const float *op = origins.data_ptr<float>(), *dp = dirs.data_ptr<float>(), *tp = t.data_ptr<float>();
  float* xp = x.data_ptr<float>();
  int64_t *fp = flat.data_ptr<int64_t>(), *rp = ray.data_ptr<int64_t>();
  at::parallel_for(0, n_rays, 256, [&](int64_t begin, int64_t end) {
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
    const float sigma = evaluated ? std::exp(std::min(c.hs[j], c.clamp)) : 0.0f;
    const float tau = sigma * c.delta[r * S + s];
    const float alpha = 1.0f - std::exp(-tau);
    cumulative += static_cast<double>(tau);
    const float w = std::exp(-(static_cast<float>(cumulative) - tau)) * alpha;
    weight_sum += w;
    if (evaluated) {
      for (int a = 0; a < 3; ++a) rgb[a] += w * (1.0f / (1.0f + std::exp(-c.hc[3 * j + a])));
      ++j;
    }
  }
  c.opacity[r] = weight_sum;
  for (int a = 0; a < 3; ++a) c.color[3 * r + a] = rgb[a] + (1.0f - weight_sum) * c.bg[3 * r + a];
}

#ifdef DUALNERF_HAVE_AVX512
// composite_ray_scalar's formulas 16 samples at a time (the cumulative sum stays sequential, in double).
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
  double cumulative = 0.0;
  for (int64_t s = 0; s < S; ++s) {
    cumulative += static_cast<double>(tau[s]);
    w[s] = tau[s] - static_cast<float>(cumulative);          // -(cumsum - tau), exponentiated below
  }
  __m512 weight_sum = _mm512_setzero_ps();
  for (int64_t s = 0; s < S_pad; s += kLanes) {
    const int64_t left = S - s;
    const __mmask16 lanes = first_lanes(left);
    const __m512 weight = _mm512_maskz_mul_ps(lanes, exp16(_mm512_loadu_ps(w + s)), _mm512_loadu_ps(alpha + s));
    _mm512_storeu_ps(w + s, weight);
    weight_sum = _mm512_add_ps(weight_sum, weight);
  }
  const int64_t n_color = 3 * (stop - first);
  for (int64_t k = 0; k < n_color; k += kLanes) {
    const int64_t left = n_color - k;
    const __mmask16 lanes = first_lanes(left);
    const __m512 x = _mm512_maskz_loadu_ps(lanes, c.hc + 3 * first + k);
    _mm512_mask_storeu_ps(rgb + k, lanes,
                          _mm512_div_ps(one, _mm512_add_ps(one, exp16(_mm512_sub_ps(_mm512_setzero_ps(), x)))));
  }
  float out[3] = {0.0f, 0.0f, 0.0f};
  for (int64_t j = first; j < stop; ++j) {
    const float weight = w[c.fp[j] - r * S];
    for (int a = 0; a < 3; ++a) out[a] += weight * rgb[3 * (j - first) + a];
  }
  const float opacity = _mm512_reduce_add_ps(weight_sum);
  c.opacity[r] = opacity;
  for (int a = 0; a < 3; ++a) c.color[3 * r + a] = out[a] + (1.0f - opacity) * c.bg[3 * r + a];
}
#endif

std::vector<torch::Tensor> composite_rays(torch::Tensor h_sigma, torch::Tensor h_color, torch::Tensor flat,
                                          torch::Tensor starts, torch::Tensor delta, torch::Tensor background,
                                          double max_h_sigma, bool vector_path) {
  for (const auto* x : {&h_sigma, &h_color, &delta, &background})
    TORCH_CHECK(x->scalar_type() == torch::kFloat32 && x->device().is_cpu(), "composite_rays: float32 CPU tensors");
  TORCH_CHECK(delta.dim() == 2 && starts.dim() == 1 && starts.size(0) == delta.size(0) + 1 &&
                  background.dim() == 2 && background.size(0) == delta.size(0) && background.size(1) == 3 &&
                  h_color.dim() == 2 && h_color.size(1) == 3 && h_color.size(0) == h_sigma.size(0) &&
                  flat.size(0) == h_sigma.size(0) && starts.scalar_type() == torch::kInt64 &&
                  flat.scalar_type() == torch::kInt64,
              "composite_rays: h_sigma (M,), h_color (M, 3), flat (M,), starts (R + 1,), delta (R, S), background (R, 3)");
  const int64_t n_rays = delta.size(0), S = delta.size(1);
  auto color = torch::empty({n_rays, 3}, delta.options());
  auto opacity = torch::empty({n_rays}, delta.options());
  h_sigma = h_sigma.contiguous();
  h_color = h_color.contiguous();
  delta = delta.contiguous();
  background = background.contiguous();
  flat = flat.contiguous();
  starts = starts.contiguous();
  const RayComposite c{h_sigma.data_ptr<float>(), h_color.data_ptr<float>(), delta.data_ptr<float>(),
                       background.data_ptr<float>(), flat.data_ptr<int64_t>(), starts.data_ptr<int64_t>(), S,
                       static_cast<float>(max_h_sigma), color.data_ptr<float>(), opacity.data_ptr<float>()};
  const bool vec = vector_path && avx512_available() && S <= 64 * kLanes;
  at::parallel_for(0, n_rays, 256, [&](int64_t begin, int64_t end) {
    std::vector<float> buf(vec ? 7 * ((S + kLanes - 1) / kLanes * kLanes) : 0);
    for (int64_t r = begin; r < end; ++r) {
#ifdef DUALNERF_HAVE_AVX512
      if (vec) {
        composite_ray_avx512(c, r, buf.data());
        continue;
      }
#endif
      composite_ray_scalar(c, r);
    }
  });
  return {color, opacity};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, module) {
  module.def("encode_forward", &encode_forward, "fused dense-grid + plane feature look-ups");
  module.def("encode_forward_pair", &encode_forward_pair, "encode_forward for two fields' tables at once");
  module.def("interleave_pair", &interleave_pair, "two fields' tables as one (cells, 4) table each");
  module.def("encode_backward", &encode_backward, "gradients of encode_forward w.r.t. the tables");
  module.def("field_inference", &field_inference, "look-ups and MLPs of one field or the fused dual field");
  module.def("ray_samples", &ray_samples, "proposal intervals and their occupancy per ray (the render sampler)");
  module.def("adam_step", &adam_step, "one Adam step on one tensor, optionally skipping zero gradients");
  module.def("adam_step_touched", &adam_step_touched, "adam_step (skip zero) on the touched chunks of a gradient buffer");
  module.def("zero_touched", &zero_touched, "zero the flagged chunks of a gradient buffer and the flags");
  module.def("encode_backward_into", &encode_backward_into, "encode_backward into persistent buffers, flagging touched chunks");
  module.def("mlp_inference", &mlp_inference, "a field's MLPs on given features (no autograd)");
  module.def("occupied_samples", &occupied_samples, "a render's occupied sample points, flat index, ray and ray offsets");
  module.def("composite_rays", &composite_rays, "a render's colour and opacity per ray from its evaluated samples");
  module.def("vector_path_available", &vector_path_available, "the AVX-512 look-up and MLP paths can run on this CPU");
  module.def("amx_path_available", &amx_path_available, "field_inference's bf16 MLPs can run on AMX tiles here");
}
