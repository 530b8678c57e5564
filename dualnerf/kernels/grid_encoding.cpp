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
#include <vector>

namespace {

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
    tables.push_back({3, g.size(2), g.size(1), 0, 0, column});
    column += g.size(1);
  }
  for (size_t i = 0; i < planes.size(); ++i) {
    const auto& p = planes[i];
    TORCH_CHECK(p.dim() == 4 && p.size(0) == 1 && p.size(2) == p.size(3), "plane must be (1, C, R, R)");
    tables.push_back({2, p.size(2), p.size(1), axes[i % 3][0], axes[i % 3][1], column});
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
  const int64_t r = t.res, c = t.channels;
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
                   int64_t end) {
  for (int64_t i = begin; i < end; ++i) {
    float acc[C] = {};
    corners(t, xp + 3 * i, [&](int64_t offset, float w) {
      for (int j = 0; j < C; ++j) acc[j] += w * table[offset + j];
    });
    float* oi = op + n_out * i + t.column;
    for (int j = 0; j < C; ++j) oi[j] = acc[j];
  }
}

void forward_any(const Table& t, const float* table, const float* xp, float* op, int64_t n_out, int64_t begin,
                 int64_t end) {
  switch (t.channels) {
    case 1: return forward_table<1>(t, table, xp, op, n_out, begin, end);
    case 2: return forward_table<2>(t, table, xp, op, n_out, begin, end);
    case 4: return forward_table<4>(t, table, xp, op, n_out, begin, end);
    case 8: return forward_table<8>(t, table, xp, op, n_out, begin, end);
  }
  TORCH_CHECK(false, "grid encoding kernel: features per table must be 1, 2, 4 or 8");
}

torch::Tensor encode_forward(torch::Tensor x, std::vector<torch::Tensor> dense, std::vector<torch::Tensor> planes) {
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
    for (size_t k = 0; k < tables.size(); ++k) forward_any(tables[k], data[k], xp, op, n_out, begin, end);
  });
  return out;
}


// The dual field's two fields (same architecture, same points): every corner's index and weight is
// computed once and applied to both fields' tables. Each output equals encode_forward's for that field
// bit for bit (the same operations per field in the same order).
template <int C>
void forward_table_pair(const Table& t, const float* table_a, const float* table_b, const float* xp, float* oa,
                        float* ob, int64_t n_out, int64_t begin, int64_t end) {
  for (int64_t i = begin; i < end; ++i) {
    float acc_a[C] = {}, acc_b[C] = {};
    corners(t, xp + 3 * i, [&](int64_t offset, float w) {
      for (int j = 0; j < C; ++j) acc_a[j] += w * table_a[offset + j];
      for (int j = 0; j < C; ++j) acc_b[j] += w * table_b[offset + j];
    });
    for (int j = 0; j < C; ++j) oa[n_out * i + t.column + j] = acc_a[j];
    for (int j = 0; j < C; ++j) ob[n_out * i + t.column + j] = acc_b[j];
  }
}

std::vector<torch::Tensor> encode_forward_pair(torch::Tensor x, std::vector<torch::Tensor> dense_a,
                                               std::vector<torch::Tensor> planes_a, std::vector<torch::Tensor> dense_b,
                                               std::vector<torch::Tensor> planes_b) {
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
    for (size_t k = 0; k < tables.size(); ++k)
      forward_table_pair<2>(tables[k], data_a[k], data_b[k], xp, oa, ob, n_out, begin, end);
  });
  return {out_a, out_b};
}

std::vector<torch::Tensor> encode_backward(torch::Tensor x, torch::Tensor grad_out, std::vector<torch::Tensor> dense,
                                           std::vector<torch::Tensor> planes) {
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
  const float* xp = x.data_ptr<float>();
  const float* gp = grad_out.data_ptr<float>();
  at::parallel_for(0, static_cast<int64_t>(tables.size()), 1, [&](int64_t begin, int64_t end) {
    for (int64_t k = begin; k < end; ++k) {
      const Table& t = tables[k];
      float* grad = data[k];
      const int64_t c = t.channels;
      for (int64_t i = 0; i < m; ++i) {
        const float* go = gp + n_out * i + t.column;
        corners(t, xp + 3 * i, [&](int64_t offset, float w) {
          for (int64_t j = 0; j < c; ++j) grad[offset + j] += w * go[j];
        });
      }
    }
  });
  return grads;
}


// Occupancy-grid density along rays (the proposal's cheap density estimate, dualnerf.rendering):
// out[r, s] = scale * density[cell(o_r + t[r, s] d_r)], cell() as OccupancyGrid.cell_index. The same
// rounded float operations as the torch reference (mul, add; (x + 1) * (0.5 r)), built with
// -ffp-contract=off, and an equivalent integer step (below), so the cells and hence the result are
// bit-for-bit those of the reference.
torch::Tensor ray_grid_density(torch::Tensor origins, torch::Tensor dirs, torch::Tensor t, torch::Tensor density,
                               double scale) {
  TORCH_CHECK(origins.scalar_type() == torch::kFloat32 && dirs.scalar_type() == torch::kFloat32 &&
                  t.scalar_type() == torch::kFloat32 && density.scalar_type() == torch::kFloat32,
              "ray_grid_density: float32 tensors expected");
  origins = origins.contiguous();
  dirs = dirs.contiguous();
  t = t.contiguous();
  density = density.contiguous();
  const int64_t n_rays = t.size(0), n_samples = t.size(1), r = density.size(0);
  TORCH_CHECK(density.dim() == 3 && density.size(1) == r && density.size(2) == r, "density must be (R, R, R)");
  auto out = torch::empty({n_rays, n_samples}, t.options());
  const float* op = origins.data_ptr<float>();
  const float* dp = dirs.data_ptr<float>();
  const float* tp = t.data_ptr<float>();
  const float* grid = density.data_ptr<float>();
  float* outp = out.data_ptr<float>();
  const float half_r = 0.5f * static_cast<float>(r), top = static_cast<float>(r - 1), fscale = static_cast<float>(scale);
  at::parallel_for(0, n_rays, 64, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      const float* o = op + 3 * i;
      const float* d = dp + 3 * i;
      for (int64_t s = 0; s < n_samples; ++s) {
        const float ts = tp[i * n_samples + s];
        int64_t cell[3];
        for (int a = 0; a < 3; ++a) {
          const float x = o[a] + ts * d[a];
          // floor, then clamp to [0, r - 1] (the reference's order) equals clamp, then truncate: both send
          // every negative value to 0. Truncation avoids std::floor's library call. NaN -> cell 0.
          const float c = (x + 1.0f) * half_r;
          cell[a] = static_cast<int64_t>(std::min(c > 0.0f ? c : 0.0f, top));
        }
        outp[i * n_samples + s] = fscale * grid[(cell[0] * r + cell[1]) * r + cell[2]];
      }
    }
  });
  return out;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, module) {
  module.def("encode_forward", &encode_forward, "fused dense-grid + plane feature look-ups");
  module.def("ray_grid_density", &ray_grid_density, "occupancy-grid density at ray samples (the proposal)");
  module.def("encode_forward_pair", &encode_forward_pair, "encode_forward for two fields' tables at once");
  module.def("encode_backward", &encode_backward, "gradients of encode_forward w.r.t. the tables");
}
