#include "mlp.h"

using namespace dualnerf;

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

constexpr int64_t kInferBlock = 256;   // samples per block: 128, 256 and 384 measured (A B C x 3,
                                       // bf16 view-update renders): 256 ~4% faster than 128, 384 between

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

FieldMlps describe_mlps(const std::vector<at::Tensor>& t, int64_t n_features, int64_t n_sh) {
  TORCH_CHECK(t.size() == 8, "field_inference: 8 MLP tensors expected (wt, b for 4 layers)");
  FieldMlps m;
  const int64_t outs[4] = {-1, -1, -1, 3};
  for (int i = 0; i < 4; ++i) {
    const auto& wt = t[2 * i];
    const auto& b = t[2 * i + 1];
    TORCH_CHECK(wt.dim() == 2 && wt.is_contiguous() && wt.scalar_type() == at::kFloat && b.dim() == 1 &&
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
// sh + r * n_sh, or sh + sh_index[r] * n_sh with an index (a render's per-ray features). density_only:
// h_sigma alone (the occupancy grid's refresh); sh and h_color are not read or written.
void field_mlps(const FieldMlps& m, const float* features, int64_t ld_features, const float* sh,
                const int64_t* sh_index, int64_t rows, Scratch& s, float* h_sigma, float* h_color, bool vector_path,
                bool density_only) {
  const Layer* l = m.layer;
  const int64_t ld_h = std::max(l[0].out_pad, l[2].out_pad), ld_d = l[1].out_pad, ld_c = l[2].in;
  apply_layer(m, 0, features, ld_features, rows, s.hidden.data(), ld_h, true, s, vector_path);
  apply_layer(m, 1, s.hidden.data(), ld_h, rows, s.density_out.data(), ld_d, false, s, vector_path);
  if (density_only) {
    for (int64_t r = 0; r < rows; ++r) h_sigma[r] = s.density_out[r * ld_d];
    return;
  }
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
// a = f_S and b = f_D. Returns (h_sigma (M,), h_color (M, 3)); density_only: (h_sigma, an empty (0, 3)
// tensor) without running the colour MLPs (sh then gives only its width: the colour MLP's SH inputs).
std::vector<at::Tensor> field_inference(at::Tensor x, at::Tensor sh, std::vector<at::Tensor> dense_a,
                                        std::vector<at::Tensor> planes_a, std::vector<at::Tensor> mlp_a,
                                        std::vector<at::Tensor> dense_b, std::vector<at::Tensor> planes_b,
                                        std::vector<at::Tensor> mlp_b, double w_density, double w_color,
                                        std::vector<at::Tensor> interleaved, std::optional<at::Tensor> sh_index,
                                        bool vector_path, bool bf16, bool amx, bool density_only) {
  TORCH_CHECK(x.dim() == 2 && x.size(1) == 3 && x.scalar_type() == at::kFloat, "x must be (M, 3) float32");
  const bool indexed = sh_index.has_value() && !density_only;
  TORCH_CHECK(sh.dim() == 2 && (indexed || density_only || sh.size(0) == x.size(0)) &&
                  sh.scalar_type() == at::kFloat,
              "sh must be (M, S) float32, or (R, S) with sh_index");
  x = x.contiguous();
  sh = sh.contiguous();
  at::Tensor sh_rows_index;
  if (indexed) {           // sample i's direction features are sh[sh_index[i]] (one row per ray)
    sh_rows_index = sh_index->contiguous();
    TORCH_CHECK(sh_rows_index.dim() == 1 && sh_rows_index.size(0) == x.size(0) &&
                    sh_rows_index.scalar_type() == at::kLong,
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
  std::vector<at::Tensor> keep;
  std::vector<const float*> data_a, data_b;
  if (dual && !interleaved.empty()) {        // interleave_pair's tables: f_S's features at +0, f_D's at +2
    TORCH_CHECK(interleaved.size() == tables.size(), "field_inference: one interleaved table per table expected");
    for (size_t k = 0; k < tables.size(); ++k) {
      TORCH_CHECK(interleaved[k].is_contiguous() && interleaved[k].scalar_type() == at::kFloat &&
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
  auto h_sigma = x.new_empty({m});
  auto h_color = x.new_empty({density_only ? 0 : m, 3});
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
  parallel_for(0, n_blocks, 1, [&](int64_t block_begin, int64_t block_end) {
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
      float* col = density_only ? nullptr : cp + 3 * begin;
      const float* sh_rows = index || density_only ? shp : shp + begin * n_sh;
      const int64_t* sh_index_rows = index ? index + begin : nullptr;
      field_mlps(mlps_a, feat_a.data(), n_features, sh_rows, sh_index_rows, rows, scratch, sig, col, vector_path,
                 density_only);
      if (!dual) continue;
      field_mlps(mlps_b, feat_b.data(), n_features, sh_rows, sh_index_rows, rows, scratch, sigma_b.data(),
                 color_b.data(), vector_path, density_only);
      // Eqs. 4-5 in the order of dualnerf.dual_field._fuse: (1 - w) * h_S + w * h_D.
      for (int64_t r = 0; r < rows; ++r) sig[r] = keep_d * sig[r] + wd * sigma_b[r];
      if (density_only) continue;
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
// interleave_pair into existing (cells, 4) tables `out` (from an earlier interleave_pair of the same table
// sizes): the second field's features always, the first field's only with write_first. A render session
// of a dual field keeps the frozen f_S's half and rewrites f_D's: half the copying, and no fresh pages.
void interleave_pair_into(std::vector<at::Tensor> out, std::vector<at::Tensor> dense_a,
                          std::vector<at::Tensor> planes_a, std::vector<at::Tensor> dense_b,
                          std::vector<at::Tensor> planes_b, bool write_first) {
  const auto tables = describe(dense_a, planes_a);
  const auto tables_b = describe(dense_b, planes_b);
  TORCH_CHECK(tables.size() == tables_b.size() && out.size() == tables.size(),
              "interleave_pair: the two fields must have the same tables, and one output per table");
  for (size_t k = 0; k < tables.size(); ++k)
    TORCH_CHECK(tables[k].res == tables_b[k].res && tables[k].channels == 2 && tables_b[k].channels == 2 &&
                    out[k].scalar_type() == at::kFloat && out[k].is_contiguous() &&
                    out[k].numel() == 4 * table_cells(tables[k]),
                "interleave_pair: the two fields must have the same tables, with 2 features each, and each "
                "output 4 floats per cell");
  std::vector<at::Tensor> keep;
  const auto data_a = table_data(dense_a, planes_a, keep);
  const auto data_b = table_data(dense_b, planes_b, keep);
  for (size_t k = 0; k < tables.size(); ++k) {
    float* o = out[k].data_ptr<float>();
    const float *a = data_a[k], *b = data_b[k];
    parallel_for(0, table_cells(tables[k]), 4096, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i) {
        if (write_first) {
          o[4 * i] = a[2 * i];
          o[4 * i + 1] = a[2 * i + 1];
        }
        o[4 * i + 2] = b[2 * i];
        o[4 * i + 3] = b[2 * i + 1];
      }
    });
  }
}

std::vector<at::Tensor> interleave_pair(std::vector<at::Tensor> dense_a, std::vector<at::Tensor> planes_a,
                                        std::vector<at::Tensor> dense_b, std::vector<at::Tensor> planes_b) {
  std::vector<at::Tensor> out;
  for (const auto& t : describe(dense_a, planes_a))
    out.push_back((dense_a.empty() ? planes_a : dense_a).front().new_empty({4 * table_cells(t)}));
  interleave_pair_into(out, dense_a, planes_a, dense_b, planes_b, true);
  return out;
}

// The MLPs alone on given features (the frozen f_S in a dual-field training step, whose look-ups the
// pair kernel already did): (h_sigma (M,), h_color (M, 3)), as field_inference computes them.
std::vector<at::Tensor> mlp_inference(at::Tensor features, at::Tensor sh, std::vector<at::Tensor> mlp,
                                      bool vector_path) {
  TORCH_CHECK(features.dim() == 2 && features.scalar_type() == at::kFloat && sh.dim() == 2 &&
                  sh.size(0) == features.size(0) && sh.scalar_type() == at::kFloat,
              "mlp_inference: (M, F) features and (M, S) sh, float32");
  features = features.contiguous();
  sh = sh.contiguous();
  const int64_t m = features.size(0), n_features = features.size(1), n_sh = sh.size(1);
  const FieldMlps mlps = describe_mlps(mlp, n_features, n_sh);
  auto h_sigma = features.new_empty({m});
  auto h_color = features.new_empty({m, 3});
  const float *fp = features.data_ptr<float>(), *shp = sh.data_ptr<float>();
  float *sp = h_sigma.data_ptr<float>(), *cp = h_color.data_ptr<float>();
  parallel_for(0, (m + kInferBlock - 1) / kInferBlock, 1, [&](int64_t block_begin, int64_t block_end) {
    Scratch scratch(mlps);
    for (int64_t blk = block_begin; blk < block_end; ++blk) {
      const int64_t begin = blk * kInferBlock, rows = std::min(m, begin + kInferBlock) - begin;
      field_mlps(mlps, fp + begin * n_features, n_features, shp + begin * n_sh, nullptr, rows, scratch, sp + begin,
                 cp + 3 * begin, vector_path, false);
    }
  });
  return {h_sigma, h_color};
}

bool vector_path_available() { return avx512_available(); }

bool amx_path_available() { return avx512_available() && amx_available(); }
