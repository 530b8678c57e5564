"""Prove a cached result reproducible: compute its key again from scratch and compare the bytes.

    recompute(store, key, registry, scratch_root, compare=None, log=None) -> Recomputed
        runs the step of `key` in a fresh store under `scratch_root` (no checkpoints: from the beginning),
        reading its upstream results from `store` and its external inputs from the paths its manifest
        recorded (their content must still hash to the key's), then compares every file with the cached one
    entries_of(store, what) -> [key]    `what` is a key (or unique prefix) or a stage name (newest first)

Recomputed.identical is True when every file has the same bytes; otherwise `differences` lists each
differing, missing or extra file with a description of how much it differs: `compare` maps a file suffix
to a function (cached path, recomputed path) -> str for the application's formats (images, tensors); JSON
files get their numeric leaves compared (the largest deltas), anything else its first differing byte.
"""
from __future__ import annotations

import json
import logging
import math
import shutil
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.engine import Job, execute_job
from pipeline.errors import UserError
from pipeline.store import MANIFEST, Store

Comparer = Callable[[Path, Path], str]


class RecomputeError(UserError):
    pass


@dataclass
class Recomputed:
    key: str
    label: str
    stage: str
    seconds: float
    identical: bool
    differences: list[str] = field(default_factory=list)


def entries_of(store: Store, what: str) -> list[str]:
    """Keys named by `what`: a stage name (every entry of that stage, newest first), else a key prefix."""
    by_stage = []
    for key, _ in store.entries():
        manifest = store.manifest(key) or {}
        if manifest.get("stage") == what:
            by_stage.append((manifest.get("finished", 0.0), key))
    if by_stage:
        return [key for _, key in sorted(by_stage, reverse=True)]
    return [store.resolve_prefix(what)]


def recompute(store: Store, key: str, registry: Mapping[str, str], scratch_root: Path,
              compare: Mapping[str, Comparer] | None = None, threads: int = 1,
              log: logging.Logger | None = None) -> Recomputed:
    manifest = store.manifest(key)
    if manifest is None or store.lookup(key) is None:
        raise RecomputeError(f"no intact cache entry {key} in {store.root}; `dualnerf cache ls` lists them.")
    stage, label = manifest["stage"], manifest.get("label", key[:12])
    if stage not in registry:
        raise RecomputeError(f"entry {key[:12]} was made by stage '{stage}', which this version does not know.")
    key_inputs = manifest["key_inputs"]
    inputs = {name: str(store.object_path(up)) for name, up in key_inputs.get("upstream", {}).items()}
    recorded = manifest.get("inputs", {})
    for name, digest in key_inputs.get("external", {}).items():
        path = recorded.get(name)
        if path is None or not Path(path).exists():
            raise RecomputeError(f"entry {key[:12]} ({label}) read the external input '{name}' from "
                                 f"{path or 'a path its manifest does not record'}, which is not there any more; "
                                 f"it cannot be recomputed here.")
        if store.hasher.hash_path(Path(path), what=f"input '{name}'") != digest:
            raise RecomputeError(f"the external input '{name}' ({path}) of entry {key[:12]} ({label}) has changed "
                                 f"since it was computed; its key no longer describes that folder.")
        inputs[name] = path
    for name, path in inputs.items():
        if name in key_inputs.get("upstream", {}) and store.lookup(key_inputs["upstream"][name]) is None:
            raise RecomputeError(f"the upstream result '{name}' of {label} is not in the cache any more; rerun "
                                 f"the workflow first.")
    scratch = Store(Path(scratch_root) / key[:16])
    if scratch.root.exists():
        shutil.rmtree(scratch.root)
    job = Job(key=key, stage_ref=registry[stage], params=manifest["params"], inputs=inputs,
              key_inputs=key_inputs, label=f"{label} (recompute)", log_path=str(scratch.root / "recompute.log"),
              cache_root=str(scratch.root), threads=threads, quiet=True)
    outcome = execute_job(job)
    if outcome.status != "done":
        raise RecomputeError(f"recomputing {label} failed: {outcome.error} (log: {job.log_path})")
    differences = compare_entries(store.object_path(key), scratch.object_path(key), compare or {})
    return Recomputed(key, label, stage, outcome.duration_s, not differences, differences)


def compare_entries(cached: Path, fresh: Path, compare: Mapping[str, Comparer]) -> list[str]:
    """One line per file that differs between two published folders of the same key (manifests aside)."""
    files = [json.loads((folder / MANIFEST).read_text())["files"] for folder in (cached, fresh)]
    out = []
    for name in sorted(set(files[0]) | set(files[1])):
        if name not in files[1]:
            out.append(f"{name}: missing from the recomputed result")
        elif name not in files[0]:
            out.append(f"{name}: only in the recomputed result")
        elif files[0][name]["sha256"] != files[1][name]["sha256"]:
            suffix = Path(name).suffix.lower()
            describe = compare.get(suffix, json_difference if suffix == ".json" else byte_difference)
            try:
                detail = describe(cached / name, fresh / name)
            except Exception as exc:  # noqa: BLE001 - a description failing must not hide the difference
                detail = f"{byte_difference(cached / name, fresh / name)} ({type(exc).__name__}: {exc})"
            out.append(f"{name}: {detail}")
    return out


def byte_difference(a: Path, b: Path) -> str:
    x, y = a.read_bytes(), b.read_bytes()
    first = next((i for i, (p, q) in enumerate(zip(x, y)) if p != q), min(len(x), len(y)))
    return f"{len(x)} vs {len(y)} bytes, first difference at byte {first}"


def _numbers(value, path=""):
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return
    if isinstance(value, (int, float)):
        yield path, float(value)
    elif isinstance(value, dict):
        for k, v in value.items():
            yield from _numbers(v, f"{path}.{k}" if path else str(k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from _numbers(v, f"{path}[{i}]")


def json_difference(a: Path, b: Path, show: int = 3) -> str:
    """The numeric leaves that differ, largest |delta| first (and whether anything else differs)."""
    x, y = (json.loads(p.read_text()) for p in (a, b))
    left, right = dict(_numbers(x)), dict(_numbers(y))
    deltas = sorted(((abs(right[k] - v) if math.isfinite(v) and math.isfinite(right[k]) else math.inf, k, v, right[k])
                     for k, v in left.items() if k in right and right[k] != v), reverse=True)
    parts = [f"{len(deltas)} number(s) differ"]
    parts += [f"{k}: {v!r} -> {w!r} (delta {d:.3g})" for d, k, v, w in deltas[:show]]
    if set(left) != set(right) or _strip_numbers(x) != _strip_numbers(y):
        parts.append("and non-numeric content differs")
    return "; ".join(parts)


def _strip_numbers(value):
    if isinstance(value, dict):
        return {k: _strip_numbers(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_strip_numbers(v) for v in value]
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return 0
    return value
