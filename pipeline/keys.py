"""Cache keys: sha256 over the canonical JSON of everything that can change a step's result.

    key = sha256(canonical_json({format, stage, version, params, upstream, external, environment, salt}))

- params: the validated params dataclass as a mapping (defaults filled in, so writing a default
  explicitly does not change the key), minus the stage's `nonsemantic_params` (threads, trace paths);
- upstream: the keys of the steps this one reads, by input name;
- external: content hashes of user files/folders, by input name (never their paths: moving a folder
  keeps the key, editing one image changes it);
- environment: versions of the stage's `packages` (read from installed metadata, without importing
  them), the `device` param if the stage has one (CPU and GPU kernels differ numerically), and the
  stage's `runtime_environment(params)`: facts of the computing process that change bits (which
  numerical code paths the CPU takes); a choice that changes bits enters the key;
- salt: store-wide; changing it disowns every earlier result (e.g. after a poisoned run).
"""
from __future__ import annotations

import dataclasses
import functools
import importlib.metadata
from typing import Any

from pipeline.canonical import canonical_value, sha256_of

FORMAT_VERSION = 1


@functools.cache
def package_version(name: str) -> str:
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return "not-installed"


def environment_fingerprint(stage_cls: type, params: Any) -> dict[str, Any]:
    """What the stage's result depends on in the process that computes it: package versions, the `device`
    param, and the stage's own `runtime_environment(params)` (e.g. which numerical code paths this CPU
    takes). A worker recomputes it and refuses to publish under a key computed for another environment."""
    env: dict[str, Any] = {"packages": {name: package_version(name) for name in sorted(stage_cls.packages)}}
    device = getattr(params, "device", None)
    if device is not None:
        env["device"] = device
    runtime = stage_cls.runtime_environment(params)
    if runtime:
        env["runtime"] = runtime
    return env


def environment_differences(expected: dict[str, Any], actual: dict[str, Any], prefix: str = "") -> list[str]:
    """'path: expected X, here Y' for every leaf where two fingerprints differ."""
    out = []
    for name in sorted(set(expected) | set(actual)):
        a, b = expected.get(name, "<absent>"), actual.get(name, "<absent>")
        if isinstance(a, dict) and isinstance(b, dict):
            out += environment_differences(a, b, f"{prefix}{name}.")
        elif a != b:
            out.append(f"{prefix}{name}: key computed for {a!r}, this worker has {b!r}")
    return out


def semantic_params(params: Any, nonsemantic: frozenset[str]) -> dict[str, Any]:
    values = {f.name: getattr(params, f.name) for f in dataclasses.fields(params)}
    return {k: v for k, v in values.items() if k not in nonsemantic}


def key_inputs(stage_cls: type, params: Any, upstream: dict[str, str], external: dict[str, str],
               salt: str) -> dict[str, Any]:
    """The full, canonical description of a step that its key hashes (also stored in the manifest)."""
    return canonical_value({
        "format": FORMAT_VERSION,
        "stage": stage_cls.name,
        "version": str(stage_cls.version),
        "params": semantic_params(params, stage_cls.nonsemantic_params),
        "upstream": dict(upstream),
        "external": dict(external),
        "environment": environment_fingerprint(stage_cls, params),
        "salt": salt,
    }, where=f"stage {stage_cls.name}")


def key_of(inputs: dict[str, Any]) -> str:
    return sha256_of(inputs)
