"""Steps, their keys, and the dry-run view of a DAG.

    External(path)                      a user file or folder, content-hashed
    Step(stage, params, inputs, label)  one invocation of a stage; inputs map input names to
                                        other Steps (upstream results) or Externals
Steps compare by identity; two distinct Step objects with the same key are computed once.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

from pipeline.errors import UserError
from pipeline.keys import key_inputs, key_of
from pipeline.registry import load_stage
from pipeline.stage import Stage, build_params


class DagError(UserError):
    pass


@dataclass(frozen=True)
class External:
    path: Path

    def __post_init__(self):
        object.__setattr__(self, "path", Path(self.path))


@dataclass(frozen=True, eq=False)
class Step:
    stage: str
    params: Mapping[str, Any] = field(default_factory=dict)
    inputs: Mapping[str, Step | External] = field(default_factory=dict)
    label: str = ""

    def __post_init__(self):
        # Frozen copies: a Step's identity must not change after its key was computed.
        object.__setattr__(self, "params", MappingProxyType(dict(self.params)))
        object.__setattr__(self, "inputs", MappingProxyType(dict(self.inputs)))

    def __repr__(self) -> str:
        return f"Step({self.stage!r}, label={self.label!r}, params={dict(self.params)!r})"

    def describe(self) -> str:
        return f"step '{self.label}' (stage {self.stage})" if self.label else f"a '{self.stage}' step"


@dataclass(frozen=True, eq=False)
class KeyedStep:
    step: Step
    key: str
    stage_cls: type[Stage]
    params: Any                       # validated params dataclass instance
    key_inputs: dict[str, Any]
    upstream: dict[str, Step]         # input name -> upstream step
    external: dict[str, Path]         # input name -> absolute user path

    @property
    def label(self) -> str:
        return self.step.label or f"{self.step.stage}-{self.key[:8]}"


def compute_keys(steps: Sequence[Step], *, registry: Mapping[str, str], store) -> dict[Step, KeyedStep]:
    """Key every step and everything upstream of it; the result is in topological order.
    Raises a UserError naming the step for unknown stages, bad params, bad inputs, missing files."""
    out: dict[Step, KeyedStep] = {}
    visiting: set[int] = set()
    salt = store.salt

    def visit(step: Step) -> KeyedStep:
        if step in out:
            return out[step]
        if id(step) in visiting:
            raise DagError(f"{step.describe()} depends on itself through its inputs.")
        visiting.add(id(step))
        where = step.describe()
        stage_cls = load_stage(registry, step.stage)
        params = build_params(stage_cls.Params, dict(step.params), where)
        upstream_keys, upstream, external_hashes, external = {}, {}, {}, {}
        for name, source in step.inputs.items():
            if isinstance(source, Step):
                if name not in stage_cls.upstream:
                    raise DagError(f"{where}: input '{name}' is not an upstream input of stage "
                                   f"'{stage_cls.name}' (upstream inputs: {list(stage_cls.upstream)}; "
                                   f"external inputs: {list(stage_cls.external)}).")
                upstream_keys[name] = visit(source).key
                upstream[name] = source
            elif isinstance(source, External):
                if name not in stage_cls.external:
                    raise DagError(f"{where}: input '{name}' is not an external (file/folder) input of "
                                   f"stage '{stage_cls.name}' (external inputs: {list(stage_cls.external)}).")
                path = source.path.absolute()
                external_hashes[name] = store.hasher.hash_path(path, what=f"{where}, input '{name}'")
                external[name] = path
            else:
                raise DagError(f"{where}: input '{name}' must be a Step or an External, got {source!r}.")
        inputs = key_inputs(stage_cls, params, upstream_keys, external_hashes, salt)
        keyed = KeyedStep(step, key_of(inputs), stage_cls, params, inputs, upstream, external)
        visiting.discard(id(step))
        out[step] = keyed
        return keyed

    try:
        for step in steps:
            visit(step)
    finally:
        store.hasher.save()
    return out


def params_dict(params: Any) -> dict[str, Any]:
    return {f.name: getattr(params, f.name) for f in dataclasses.fields(params)}


def step_state(store, key: str) -> str:
    """cached / running / partial (checkpoints from an earlier attempt exist) / pending. `running` means a
    lease whose holder is not provably dead (telling a silent holder on another host from a live one takes
    watching its heartbeat for a ttl; a waiting worker does that, a status display does not)."""
    if store.has(key):
        return "cached"
    holder = store.lease_holder(key)
    if holder is not None and not holder.dead_here():
        return "running"
    checkpoints = store.scratch_path(key) / "checkpoints"
    if checkpoints.is_dir() and any(p.name.isdigit() for p in checkpoints.iterdir()):
        return "partial"
    return "pending"


def dry_run(steps: Sequence[Step], *, registry: Mapping[str, str], store) -> list[tuple[str, str, str]]:
    """(label, key prefix, state) for every step, in execution order, without running anything."""
    keyed = compute_keys(steps, registry=registry, store=store)
    return [(k.label, k.key[:12], step_state(store, k.key)) for k in keyed.values()]


def resolve_results(steps: Sequence[Step], *, registry: Mapping[str, str], store) -> dict[Step, Path | None]:
    """The verified published folder of each step, or None where it has not been computed."""
    keyed = compute_keys(steps, registry=registry, store=store)
    return {step: store.lookup(keyed[step].key) for step in steps}
