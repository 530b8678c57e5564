"""The kernel build survives what a killed build leaves behind."""

import os
import shutil
import subprocess
import sys

import pytest
from torch.utils.cpp_extension import _get_build_directory

from dualnerf import kernels

pytestmark = pytest.mark.skipif(kernels.grid_kernel() is None, reason="no C++ toolchain: nothing is built")


def test_a_stale_torch_lock_from_a_killed_build_does_not_hang_the_next_load(tmp_path):
    # A build killed mid-way leaves torch's plain `lock` file in the build folder; torch's loader then
    # waits on it forever (a CI run hung at set-up for 90 min). Copy the built extension into a fresh
    # extensions root, leave such a lock in it, and load it in a new process.
    name = kernels.build_name()
    built = _get_build_directory(name, verbose=False)
    root = tmp_path / "extensions"
    shutil.copytree(built, root / name)
    (root / name / "lock").write_text("")
    env = dict(os.environ, TORCH_EXTENSIONS_DIR=str(root))
    done = subprocess.run([sys.executable, "-c", "from dualnerf import kernels; print(kernels.kernel_name())"],
                          check=False, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "fused-cpp"
    assert not (root / name / "lock").exists()


# Kernel outputs of every kind (look-ups forward and backward, fp32 inference of one field and of the dual
# field, a training forward and backward through the MLP kernels) hashed, for comparing builds.
_OUTPUTS_HASH = r"""
import hashlib, torch
from dualnerf import kernels
from dualnerf.fields import FieldConfig, RadianceField
torch.set_num_threads(1)
config = FieldConfig(grid_resolutions=(8, 16, 32), plane_resolutions=(32, 64), hidden_width=64)
def field(seed):
    model = RadianceField(config, torch.Generator().manual_seed(seed))
    with torch.no_grad():
        for p in model.parameters():
            p.add_(torch.randn(p.shape, generator=torch.Generator().manual_seed(seed + 1)) * 0.3)
    return model
a, b = field(0), field(5)
g = torch.Generator().manual_seed(3)
x = torch.rand(1237, 3, generator=g) * 2.2 - 1.1
d = torch.nn.functional.normalize(torch.randn(1237, 3, generator=g), dim=-1)
sh = a.direction_features(d)
module = kernels.grid_kernel()
out = [module.encode_forward_pair(x, *a.grid_tables(), *b.grid_tables(), kernels.vector_path())]
features = module.encode_forward(x, *a.grid_tables(), kernels.vector_path())
out.append(module.encode_backward(x, torch.randn(features.shape, generator=g), *a.grid_tables(), kernels.vector_path()))
with torch.no_grad():
    out.append(kernels.field_inference(x, sh, a.grid_tables(), a.mlp_layers()))
    out.append(kernels.field_inference(x, sh, a.grid_tables(), a.mlp_layers(), second=(b.grid_tables(), b.mlp_layers()),
                                       blend=(0.3, 0.1)))
sigma, color = a(x, d)
(sigma.square().sum() + (color * torch.rand(color.shape, generator=g)).sum()).backward()
out.append([p.grad for p in a.parameters() if p.grad is not None])
digest = hashlib.sha256()
def add(value):
    if isinstance(value, torch.Tensor):
        digest.update(value.detach().contiguous().numpy().tobytes())
    else:
        for v in value:
            add(v)
add(out)
print(kernels.build_name(), digest.hexdigest())
"""


def _outputs_hash(build: str) -> tuple[str, str]:
    env = dict(os.environ, DUALNERF_KERNEL_BUILD=build)
    done = subprocess.run([sys.executable, "-c", _OUTPUTS_HASH], check=False, env=env, capture_output=True,
                          text=True, timeout=900)
    assert done.returncode == 0, done.stderr
    name, digest = done.stdout.split()[-2:]
    return name, digest


@pytest.mark.slow
def test_the_generic_build_gives_the_bits_of_this_cpus_build():
    # The generic build (no AVX-512 code, no -mavx2 -mfma: what an x86-64 CPU with neither runs; scalar
    # std::fma through libm) against this CPU's build (its AVX-512 code, with the scalar code compiled with
    # -mavx2 -mfma): the same chains of fused multiply-adds, so the same bits, or a result would depend on
    # the CPU. It compiles a second extension (~1.5-2 min), so it runs where the AVX-512 code makes the rest
    # of the suite fast; on a CPU without AVX-512 the AVX2 tiles are compared with the scalar code of the
    # same build in process (test_kernel_threads.py, test_inference_kernel.py), and the scalar code with
    # -mavx2 -mfma is the same machine code as on the AVX-512 CPUs that run this test.
    if kernels.vector_code() != "avx512":
        pytest.skip("no AVX-512 here: the AVX2 tiles are compared in process; the generic build runs on AVX-512 CPUs")
    name, digest = _outputs_hash("")
    generic_name, generic_digest = _outputs_hash("generic")
    assert name == kernels.build_name() and generic_name.endswith("_portable")
    assert name.endswith("_avx2") == (kernels.isa_flags() == ["-mavx2", "-mfma"])
    assert generic_digest == digest, f"{generic_name} and {name} give different bits"


def test_the_avx2_flags_follow_the_cpu_and_the_build_setting(monkeypatch):
    monkeypatch.setattr(kernels, "cpu_flags", lambda: frozenset({"avx2", "fma", "sse2"}))
    assert kernels.isa_flags() == ["-mavx2", "-mfma"] and kernels.build_name().endswith("_avx2")
    monkeypatch.setattr(kernels, "cpu_flags", lambda: frozenset({"avx2", "sse2"}))     # AVX2 without FMA
    assert kernels.isa_flags() == [] and not kernels.build_name().endswith("_avx2")
    monkeypatch.setattr(kernels, "cpu_flags", lambda: frozenset({"avx2", "fma"}))
    monkeypatch.setenv("DUALNERF_KERNEL_BUILD", "generic")
    assert kernels.isa_flags() == [] and kernels.build_name().endswith("_portable")
