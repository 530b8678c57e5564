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
