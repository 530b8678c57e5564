"""Run a benchmark module as an earlier commit has it, for a before/after table in the same run.

    profile_revision(revision, module, argv) -> text printed by that commit's `python -m <module> <argv>`
    parse_edit_profile(text) -> {variant: {"iteration_ms", "step_ms", "update_ms"}, "dual_over_single"}
    parse_render_cache_profile(text) -> {"f_S" | "dual": (fitted tables s, cache-sized s)}

The commit is checked out into a temporary git worktree (the repository's history must hold it; a
shallow clone may not) and run with this environment's Python and packages: its own sources, its own
kernel build (compiled on first use, cached like any other). Nothing of the checkout stays behind.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NESTED_RUN = "DUALNERF_BENCH_REVISION"       # set in the environment of a run at an earlier commit


class RevisionUnavailable(RuntimeError):
    """The commit cannot be checked out here (not a git checkout, or the history lacks it)."""


def profile_revision(revision: str, module: str, argv: list[str]) -> str:
    """stdout of `python -m module argv` run from a worktree of `revision` (stderr goes to ours)."""
    with tempfile.TemporaryDirectory(prefix="bench-revision-") as tmp:
        tree = Path(tmp) / "tree"
        added = subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), revision],
                               check=False, capture_output=True, text=True)
        if added.returncode != 0:
            raise RevisionUnavailable(f"cannot check out {revision}: {added.stderr.strip() or added.stdout.strip()}")
        try:
            # NESTED_RUN tells a profile that can compare itself not to start another comparison.
            env = {**os.environ, "PYTHONPATH": str(tree), NESTED_RUN: revision}
            done = subprocess.run([sys.executable, "-m", module, *argv], cwd=tree, env=env, text=True,
                                  stdout=subprocess.PIPE, check=False)
            if done.returncode != 0:
                raise RevisionUnavailable(f"{module} at {revision} exited with {done.returncode}")
            return done.stdout
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)],
                           check=False, capture_output=True)


_VARIANT = re.compile(r"^(?P<label>.+?): (?P<n>\d+) iterations, \d+ view updates, [\d.]+ s loop "
                      r"\(per iteration (?P<ms>[\d.]+) ms\)")
_TOTAL = re.compile(r"^\s+(?P<part>step|update) total\s+[\d.]+\s+[\d.]+%\s+(?P<ms>[\d.]+) ms/")


def parse_edit_profile(text: str) -> dict:
    """The per-variant summary lines of benchmarks.profile_edit's output (every version prints them)."""
    out: dict = {}
    label = None
    for line in text.splitlines():
        if match := _VARIANT.match(line):
            label = match["label"]
            out[label] = {"iteration_ms": float(match["ms"])}
        elif (match := _TOTAL.match(line)) and label is not None:
            out[label][f"{match['part']}_ms"] = float(match["ms"])
        elif line.startswith("dual / single loop time:"):
            out["dual_over_single"] = float(line.split(":")[1])
    return out


_CACHE_ROW = re.compile(r"^\s*(?P<label>f_S|dual)\s+(?P<fitted>[\d.]+)\s+(?P<cached>[\d.]+)\s+-?\d+%\s*$")


def parse_render_cache_profile(text: str) -> dict[str, tuple[float, float]]:
    """The table rows of benchmarks.profile_render_cache's output (every version prints them)."""
    return {m["label"]: (float(m["fitted"]), float(m["cached"])) for m in map(_CACHE_ROW.match, text.splitlines()) if m}
