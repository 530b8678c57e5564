"""Fused CPU kernels for the field's feature-grid look-ups, with the plain torch code as the reference.

API:
    grid_kernel() -> module | None      the compiled kernel (built on first use), or None when unavailable
    kernel_name() -> str                "fused-cpp" or "torch-reference": what features() runs (for manifests)
    fused_grid_features(x (M,3), dense_grids, planes) -> (M, F)   autograd-aware: gradients reach the tables
    fused_pair_features(x, dense_a, planes_a, dense_b, planes_b) -> (F_a detached, F_b)   a DualField's two
        fields in one pass (the index and weight maths shared; f_S, the first, is frozen)
    can_fuse(x, features) -> bool;  can_fuse_pair(x, features) -> bool
    field_inference(x (M,3), sh (M,S), tables, layers, second=None, blend=(0, 0)) -> (h_sigma (M,), h_color (M,3))
        without autograd: one field's look-ups and MLPs in one pass, or the dual field's two fused by eqs. 4-5
        (`second` = f_D's (tables, layers); tables = (dense grids, planes), layers = its 4 nn.Linear)
    mlp_inference(features (M,F), sh (M,S), layers) -> (h_sigma, h_color)   the MLP part alone, no autograd
    mlp_precision(precision)            context: field_inference's MLPs in "fp32" (default) or "bf16"
    bf16_path_name() -> str             "amx-tiles" | "emulated": how bf16 MLPs run on this CPU (manifests)
    vector_path() -> bool               the vector code runs (DUALNERF_KERNEL_VECTOR; =0: scalar, for tests)
    vector_code() -> str                "avx512" | "avx2" | "none": which vector code runs here
    isa_flags() -> list                 -mavx2 -mfma where the building CPU has them (in the build's name)
    grid_kernel().occupied_samples / composite_rays / ray_samples: a render's packing, compositing and
        sampler (called by dualnerf.rendering, whose torch code is their reference)
    can_infer(x, features) -> bool      field_inference takes these points (2 features per table)
    runs_on(x) -> bool                  the kernel is built and x is a float32 CPU tensor
    TableGradients(tables)              persistent gradient buffers + touched-chunk flags that the look-up
        kernels' backward fills inside `with table_gradients.collect():` (consumed by dualnerf.optim.FieldAdam)

Why: a field evaluation reads 13 feature tables (4 dense grids, 9 planes). Through F.grid_sample that is
13 calls with a (C, M) intermediate, a transpose and a concatenation each; the profile
(benchmarks.profile_edit) put the look-ups at ~60% of a render. `lookups.cpp` does them in one pass
over the points on channels-last tables, table by table within blocks of neighbouring samples, and its
backward accumulates each table's gradient on one thread in point order (no races, repeatable sums).

The kernel is compiled with torch.utils.cpp_extension on first use (~30 s, cached under
$TORCH_EXTENSIONS_DIR or ~/.cache/torch_extensions). Without a C++ compiler, on a non-CPU device, or with
DUALNERF_KERNELS=0 the reference path (dualnerf.encoding's modules on F.grid_sample) runs instead; the two
agree to float32 rounding (tests/test_grid_kernel.py), not bit for bit, so results record which one ran.
"""
from __future__ import annotations

import fcntl
import hashlib
import logging
import os
import subprocess
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import torch

from dualnerf.cpu import cpu_flags

# One extension from the files beside this one (kernels.h says which does what).
_SOURCES = sorted(Path(__file__).parent.glob("*.cpp"))
_HEADERS = sorted(Path(__file__).parent.glob("*.h"))
_lock = threading.Lock()
_state: dict = {}
log = logging.getLogger(__name__)


def grid_kernel():
    """The compiled extension module, or None (reference path). Built once per process, then cached on disk."""
    if os.environ.get("DUALNERF_KERNELS", "1") == "0":
        return None
    with _lock:
        if "module" not in _state:
            _state["module"] = _build()
    return _state["module"]


def _build(attempts: int = 3):
    try:
        from torch.utils.cpp_extension import _get_build_directory, load

        name = build_name()
        build_directory = Path(_get_build_directory(name, verbose=False))
        portable = ["-DDUALNERF_NO_AVX512"] if _portable_build() else []
        for attempt in range(attempts):
            try:
                with _builder_lock(build_directory):
                    return load(name, [str(p) for p in _SOURCES], build_directory=str(build_directory),
                                extra_cflags=["-O3", "-fopenmp", "-ffp-contract=off", *portable, *isa_flags()],
                                extra_ldflags=["-fopenmp"], verbose=False)
            # A process on another node sharing this home (where the lock may not reach) replaced the build
            # folder under torch's lock: transient, and falling back would change this process's keys.
            except FileNotFoundError:
                if attempt == attempts - 1:
                    raise
                time.sleep(1.0 + attempt)
    # No compiler, no ninja, a failed build: the reference path still works.
    except (OSError, RuntimeError, ImportError, subprocess.CalledProcessError) as error:
        log.warning("dualnerf: the C++ field kernels could not be built (%s); using the plain torch "
                    "reference path, which is ~2x slower. Install a C++ compiler and ninja, or set "
                    "DUALNERF_KERNELS=0 to silence this.", str(error).splitlines()[0] if str(error) else error)
        return None


@contextmanager
def _builder_lock(build_directory: Path):
    """Serialise builders of one extension with a lock the OS releases when its holder dies, and clear
    torch's own lock file under it. torch's `lock` is a plain file that a build killed mid-way (a test
    timeout, Ctrl-C, a CI kill) leaves behind, and every later load of that extension then waits on it
    forever; since every live builder holds this lock first, a `lock` file found while holding it is stale."""
    build_directory.mkdir(parents=True, exist_ok=True)
    with open(build_directory / "dualnerf-builder.lock", "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            (build_directory / "lock").unlink(missing_ok=True)
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def build_name() -> str:
    """The extension's name: named by the sources' and headers' content, so torch rebuilds on changed
    sources only, and a changed header never reuses an extension compiled from the old one."""
    digest = hashlib.sha256(b"".join(p.read_bytes() for p in _SOURCES + _HEADERS)).hexdigest()[:12]
    return (f"dualnerf_field_kernels_{digest}" + ("_portable" if _portable_build() else "")
            + ("_avx2" if isa_flags() else ""))


def _portable_build() -> bool:
    """DUALNERF_KERNEL_BUILD=portable: compile without the AVX-512 code (what a CPU or compiler without
    it runs; for tests: the results must be the same bits); =generic: without the AVX2 flags too
    (isa_flags; what an x86-64 CPU with neither runs)."""
    return os.environ.get("DUALNERF_KERNEL_BUILD", "") in ("portable", "generic")


def isa_flags() -> list[str]:
    """-mavx2 -mfma where this x86-64 CPU has AVX2 and FMA (DUALNERF_KERNEL_BUILD=generic: never).

    Why: the portable code is what a CPU without AVX-512 runs, and without these flags every std::fma in
    it is a call into libm and no loop is vectorised (a field evaluation ~30x slower than with them). With
    them the compiler emits the FMA instruction for std::fma, which rounds exactly as the library call
    does, and vectorises only element-wise loops (-ffp-contract=off, no -ffast-math: no sum is reordered
    and no a * b + c contracted), so the bits stay those of the generic build. The flags are chosen from
    the CPU that builds, and they are in the extension's name: a home folder shared with a CPU without
    AVX2 (a cluster node) never loads this build there."""
    if os.environ.get("DUALNERF_KERNEL_BUILD", "") == "generic":
        return []
    return ["-mavx2", "-mfma"] if cpu_flags() >= {"avx2", "fma"} else []


def kernel_name() -> str:
    return "fused-cpp" if grid_kernel() is not None else "torch-reference"


class TableGradients:
    """Persistent gradient buffers for feature tables, which the kernels' backward fills instead of
    handing autograd freshly zero-filled (M-entry) gradients, with a flag per chunk of 16 values saying
    which chunks a batch touched. dualnerf.optim.FieldAdam updates the touched chunks only and zeroes them
    again, so a training step costs in proportion to what its rays touch, not to the 13M table entries
    (benchmarks.profile_edit: the dense zero fill and optimiser pass were a quarter of a step).

    Used by a trainer: `with table_gradients.collect(): <forward>`; a forward of the fused look-up kernels
    inside it whose trainable tables are all registered here sends their gradients here (p.grad stays
    None); any other forward uses autograd as usual. The gradients are the same bits either way."""

    CHUNK = 16

    def __init__(self, tables):
        self.buffers = {id(t): (t, torch.zeros_like(t, memory_format=torch.preserve_format),
                                torch.zeros(-(-t.numel() // self.CHUNK), dtype=torch.uint8)) for t in tables}

    def holds(self, tables) -> bool:
        return bool(tables) and all(id(t) in self.buffers for t in tables)

    def gradient(self, table) -> tuple[torch.Tensor, torch.Tensor] | None:
        """(buffer, touched flags) of a registered table, else None."""
        entry = self.buffers.get(id(table))
        return None if entry is None else entry[1:]

    def add(self, x, grad, dense, planes) -> None:
        tables = [*dense, *planes]
        grid_kernel().encode_backward_into(x, grad, list(dense), list(planes),
                                           [self.buffers[id(t)][1] for t in tables],
                                           [self.buffers[id(t)][2] for t in tables], vector_path())

    def clear(self) -> None:
        for _, buffer, touched in self.buffers.values():
            grid_kernel().zero_touched(buffer, touched)

    @contextmanager
    def collect(self):
        previous = getattr(_collector, "sink", None)
        _collector.sink = self
        try:
            yield self
        finally:
            _collector.sink = previous


_collector = threading.local()


def _sink_for(tables) -> TableGradients | None:
    sink = getattr(_collector, "sink", None)
    return sink if sink is not None and sink.holds(tables) else None


class _FusedGridFeatures(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, n_dense, *tables):
        module = grid_kernel()
        dense, planes = list(tables[:n_dense]), list(tables[n_dense:])
        ctx.save_for_backward(x, *tables)
        ctx.n_dense = n_dense
        ctx.sink = _sink_for(tables)
        return module.encode_forward(x, dense, planes, vector_path())

    @staticmethod
    def backward(ctx, grad):
        x, *tables = ctx.saved_tensors
        n = ctx.n_dense
        # No gradient for the sample positions: they come from rays, which are never trained.
        if ctx.sink is not None:
            ctx.sink.add(x, grad, tables[:n], tables[n:])
            return (None, None, *([None] * len(tables)))
        grads = grid_kernel().encode_backward(x, grad, list(tables[:n]), list(tables[n:]), vector_path())
        return (None, None, *grads)


class _FusedPairFeatures(torch.autograd.Function):
    """Two fields' features in one pass; the first field (the frozen f_S) gets no gradient."""

    @staticmethod
    def forward(ctx, x, n_dense, n_tables, *tables):
        first, second = tables[:n_tables], tables[n_tables:]
        out_first, out_second = grid_kernel().encode_forward_pair(
            x, list(first[:n_dense]), list(first[n_dense:]), list(second[:n_dense]), list(second[n_dense:]),
            vector_path())
        ctx.mark_non_differentiable(out_first)
        ctx.save_for_backward(x, *second)
        ctx.n_dense, ctx.n_tables = n_dense, n_tables
        ctx.sink = _sink_for(second)
        return out_first, out_second

    @staticmethod
    def backward(ctx, grad_first, grad_second):
        x, *second = ctx.saved_tensors
        n = ctx.n_dense
        if ctx.sink is not None:
            ctx.sink.add(x, grad_second, second[:n], second[n:])
            return (None, None, None, *([None] * (2 * ctx.n_tables)))
        grads = grid_kernel().encode_backward(x, grad_second, list(second[:n]), list(second[n:]),
                                              vector_path())
        return (None, None, None, *([None] * ctx.n_tables), *grads)


def fused_pair_features(x: torch.Tensor, first_dense, first_planes, second_dense, second_planes):
    """fused_grid_features for two fields with equal tables at the same points, in one pass (each corner's
    index and weight computed once): (features of the first, detached; features of the second, with
    gradients to its tables). Each equals fused_grid_features of that field bit for bit."""
    if x.requires_grad:
        raise ValueError("fused_pair_features: no gradient w.r.t. the sample positions")
    first, second = [*first_dense, *first_planes], [*second_dense, *second_planes]
    if len(first) != len(second):
        raise ValueError("fused_pair_features: the two fields must have the same tables")
    return _FusedPairFeatures.apply(x, len(first_dense), len(first), *first, *second)


def fused_grid_features(x: torch.Tensor, dense_grids, planes) -> torch.Tensor:
    """Features of points x: the dense grids' (each C columns, in order), then the planes' (level-major,
    xy/xz/yz within a level), as DenseGridEncoding and PlaneGridEncoding concatenated."""
    if x.requires_grad:
        raise ValueError("fused_grid_features: no gradient w.r.t. the sample positions; use the reference "
                         "encodings (dualnerf.encoding) when x requires grad")
    return _FusedGridFeatures.apply(x, len(dense_grids), *dense_grids, *planes)


def _layer_tensors(layers) -> list[torch.Tensor]:
    """(W^T zero-padded to (in, 16k), bias zero-padded to 16k) per nn.Linear: the inference kernel's layout."""
    return _forward_layout(_parameters(layers))


def interleave_pair(first_tables, second_tables, into: list[torch.Tensor] | None = None,
                    write_first: bool = True) -> list[torch.Tensor] | None:
    """Two fields' (dense grids, planes) as one (cells, 4) table each (first's 2 features, then second's),
    for field_inference(..., interleaved=): both fields' corner from one cache line. None where the kernel
    cannot take them (not built, not float32 CPU tables with 2 features each).
    `into`: an earlier result for tables of the same sizes, rewritten in place and returned (the second
    field's half always, the first's only with write_first: a frozen first field's half stays valid)."""
    module = grid_kernel()
    tables = [*first_tables[0], *first_tables[1], *second_tables[0], *second_tables[1]]
    if module is None or not all(t.device.type == "cpu" and t.dtype == torch.float32 and t.shape[1] == 2
                                 for t in tables):
        return None
    args = (list(first_tables[0]), list(first_tables[1]), list(second_tables[0]), list(second_tables[1]))
    with torch.no_grad():
        if into is None:
            return module.interleave_pair(*args)
        module.interleave_pair_into(into, *args, bool(write_first))
        return into


def field_inference(x: torch.Tensor, sh: torch.Tensor, tables, layers, second=None,
                    blend: tuple[float, float] = (0.0, 0.0), interleaved: list[torch.Tensor] | None = None,
                    sh_index: torch.Tensor | None = None,
                    density_only: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """(h_sigma, h_color) of one field at points x with per-point direction SH features `sh`, computed block
    by block in cache (look-ups, both MLPs) instead of through torch's (M, width) intermediates. `tables` =
    (dense grids, planes) and `layers` = (density hidden, density out, colour hidden, colour out) nn.Linear.
    With `second` = (tables, layers) of f_D: the dual field, h = (1 - w) h_S + w h_D with blend = (w_density,
    w_color) (eqs. 4-5). Agrees with the torch path (features(), heads()) to float32 rounding; one
    sample's result does not depend on the others, the block size or the thread count. `interleaved`:
    interleave_pair(tables, second's tables), read instead of the two fields' tables (the same bits).
    `sh_index` (M,) int64: sample i's SH features are sh[sh_index[i]] (sh holds one row per ray), the same
    values as passing sh[sh_index] without writing that (M, S) copy. `density_only`: h_sigma alone, the
    colour MLPs skipped (the occupancy grid's refresh); h_color is then (0, 3), and `sh` only gives the
    number of SH features (e.g. an empty (0, S) tensor). h_sigma is the same bits either way."""
    _refuse_autograd("field_inference", x, sh, *tables[0], *tables[1], *_parameters(layers),
                     *([] if second is None else [*second[0][0], *second[0][1], *_parameters(second[1])]))
    dense, planes = tables
    second_dense, second_planes, second_layers = [], [], []
    if second is not None:
        (second_dense, second_planes), second_layers = second[0], _layer_tensors(second[1])
    return tuple(grid_kernel().field_inference(
        x, sh, list(dense), list(planes), _layer_tensors(layers), list(second_dense), list(second_planes),
        second_layers, float(blend[0]), float(blend[1]), [] if second is None or interleaved is None else interleaved,
        sh_index, vector_path(), current_mlp_precision() == "bf16", _amx_path(), bool(density_only)))


def _forward_layout(params) -> list[torch.Tensor]:
    """(W^T zero-padded to (in, 16k), bias zero-padded to 16k) per layer from its (weight, bias) tensors."""
    out = []
    for weight, bias in zip(params[::2], params[1::2]):
        n_out, n_in = weight.shape
        padded = -(-n_out // 16) * 16
        weight_t = weight.new_zeros(n_in, padded)
        weight_t[:, :n_out] = weight.detach().t()
        bias_padded = bias.new_zeros(padded)
        bias_padded[:n_out] = bias.detach()
        out += [weight_t, bias_padded]
    return out


def _backward_layout(params) -> list[torch.Tensor]:
    """Each layer's weight (out, in) with its columns zero-padded to a multiple of 16 (dx = dy W)."""
    out = []
    for weight in params[::2]:
        n_out, n_in = weight.shape
        padded = weight.new_zeros(n_out, -(-n_in // 16) * 16)
        padded[:, :n_in] = weight.detach()
        out.append(padded)
    return out


class _TrainHeads(torch.autograd.Function):
    """A field's MLPs with autograd on the training kernels (mlp_train.cpp): the same bits on any thread
    count and on the AVX-512 and portable paths."""

    @staticmethod
    def forward(ctx, features, sh, sh_index, *params):
        h_sigma, h_color, hidden_density, color_in, hidden_color = grid_kernel().mlp_train_forward(
            features, sh, sh_index, _forward_layout(params), vector_path())
        ctx.save_for_backward(features, hidden_density, color_in, hidden_color, *params)
        ctx.n_sh = sh.shape[1]
        return h_sigma, h_color

    @staticmethod
    def backward(ctx, grad_sigma, grad_color):
        features, hidden_density, color_in, hidden_color, *params = ctx.saved_tensors
        if grad_sigma is None:
            grad_sigma = features.new_zeros(features.shape[0])
        if grad_color is None:
            grad_color = features.new_zeros(features.shape[0], 3)
        out = grid_kernel().mlp_train_backward(grad_sigma, grad_color, features, hidden_density, color_in,
                                               hidden_color, _forward_layout(params), _backward_layout(params),
                                               ctx.n_sh, vector_path())
        return (out[0] if ctx.needs_input_grad[0] else None, None, None, *out[1:])


def train_heads(features: torch.Tensor, sh: torch.Tensor, layers,
                sh_index: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(h_sigma, h_color) of a field's 4 MLP layers (density hidden, density out, colour hidden, colour out)
    with autograd to the features and the layers' parameters: the training counterpart of mlp_inference.
    Row i's direction features are sh[i], or sh[sh_index[i]] with an index. The weight gradients are sums
    over samples in a fixed grouping (mlp_train.cpp), so a training step's bits do not depend on the
    thread count; they agree with torch's nn.Linear to float32 rounding."""
    params = _parameters(layers)
    return _TrainHeads.apply(features, sh.detach(), sh_index, *params)


def can_train(features: torch.Tensor, sh: torch.Tensor) -> bool:
    """train_heads takes these inputs: the kernel is built, float32 CPU features and sh."""
    return runs_on(features) and runs_on(sh)


def set_threads(n: int) -> None:
    """The kernels' thread count (their results do not depend on it); no-op without the kernel."""
    module = grid_kernel()
    if module is not None:
        module.set_threads(max(1, int(n)))


def kernel_threads() -> int:
    module = grid_kernel()
    return module.get_threads() if module is not None else 0


def mlp_inference(features: torch.Tensor, sh: torch.Tensor, layers) -> tuple[torch.Tensor, torch.Tensor]:
    """field_inference's MLP part on given features (M, F): (h_sigma, h_color) without autograd."""
    _refuse_autograd("mlp_inference", features, sh, *_parameters(layers))
    return tuple(grid_kernel().mlp_inference(features, sh, _layer_tensors(layers), vector_path()))


MLP_PRECISIONS = ("fp32", "bf16")
_precision = threading.local()


@contextmanager
def mlp_precision(precision: str):
    """Inside this block (this thread), field_inference runs the MLPs in `precision`: "fp32", or "bf16"
    (each layer's inputs and weights rounded to bfloat16, products summed in float32; on AMX tiles where
    the CPU has them, ~4x faster MLPs). For renders that tolerate ~1e-3 colour differences: the IDU's
    view updates, which an editor re-noises anyway. Evaluation, probes and training stay fp32. The torch
    reference path (no kernel) always computes in fp32."""
    if precision not in MLP_PRECISIONS:
        raise ValueError(f"mlp_precision must be one of {MLP_PRECISIONS}, got {precision!r}")
    previous = getattr(_precision, "value", "fp32")
    _precision.value = precision
    try:
        yield
    finally:
        _precision.value = previous


def current_mlp_precision() -> str:
    return getattr(_precision, "value", "fp32")


def bf16_path_name() -> str:
    """How field_inference's bf16 MLPs run here: "amx-tiles" or "emulated" (rounded values through the
    float32 layer code); the two differ in the order of float32 sums only."""
    module = grid_kernel()
    return "amx-tiles" if module is not None and _amx_path() and module.amx_path_available() else "emulated"


def _amx_path() -> bool:
    """AMX tiles for bf16 MLPs where the CPU has them (DUALNERF_KERNEL_AMX=0: the emulation, for tests)."""
    return vector_path() and os.environ.get("DUALNERF_KERNEL_AMX", "1") != "0"


def _parameters(layers) -> list[torch.Tensor]:
    return [t for layer in layers for t in (layer.weight, layer.bias)]


def _refuse_autograd(name: str, *tensors: torch.Tensor) -> None:
    """The inference kernels record no autograd graph: refuse inputs that would need one."""
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        raise ValueError(f"{name}: inference only, but an input requires grad; run under torch.no_grad() or "
                         "use the autograd path (features() and heads())")


def vector_path() -> bool:
    """The AVX-512 code where the CPU has it, else the AVX2 layer and look-up code where the build has it
    (DUALNERF_KERNEL_VECTOR=0: the scalar code, for tests; all give the same bits)."""
    return os.environ.get("DUALNERF_KERNEL_VECTOR", "1") != "0"


def vector_code() -> str:
    """Which vector code vector_path() runs on this CPU and build: "avx512", "avx2" (the MLP layers and the
    look-ups; the sampler and compositing run their scalar code) or "none"."""
    module = grid_kernel()
    if module is None:
        return "none"
    return "avx512" if module.vector_path_available() else ("avx2" if isa_flags() else "none")


def can_infer(x: torch.Tensor, features: int) -> bool:
    """field_inference takes these points: as can_fuse, with 2 features per table (whether autograd is
    needed is the caller's to check: RadianceField.can_infer)."""
    return features == 2 and can_fuse(x, features)


def runs_on(x: torch.Tensor) -> bool:
    """The kernel is built and takes x: a float32 CPU tensor."""
    return x.device.type == "cpu" and x.dtype == torch.float32 and grid_kernel() is not None


def can_fuse(x: torch.Tensor, features: int) -> bool:
    """The kernel handles float32 CPU points with 1, 2, 4 or 8 features per table and no grad w.r.t. x."""
    return not x.requires_grad and features in (1, 2, 4, 8) and runs_on(x)


def can_fuse_pair(x: torch.Tensor, features: int) -> bool:
    """fused_pair_features applies: as can_fuse, with 2 features per table (the kernel's pair path)."""
    return features == 2 and can_fuse(x, features)
