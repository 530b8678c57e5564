"""The stage contract: what a pipeline step declares and what it may use while it runs.

The engine (store, scheduler, executors) only sees this interface; it never imports model code.
A stage is a class with class-level declarations and a `run(ctx)` method:

    @dataclass(frozen=True)
    class FitParams:
        iterations: int = 3000
        seed: int = 0
        num_threads: int = 0          # non-semantic: listed in `nonsemantic_params`

    class FitStage(Stage):
        name = "fit"
        version = "3"                 # bump when a code change alters results
        Params = FitParams
        upstream = ("dataset",)       # names of other steps' results this stage reads
        external = ()                 # names of user files/folders this stage reads
        resources = Resources(cpus=2, gpus=0, memory_gb=3)   # per step: resources_for(params)
        nonsemantic_params = frozenset({"num_threads"})
        packages = ("torch",)         # their versions enter the key (environment fingerprint)
        # optional: runtime_environment(params) -> dict (keyed), provenance() -> dict (manifest only)

        def run(self, ctx: StageContext) -> None:
            data_dir = ctx.inputs["dataset"]          # a published, read-only result folder
            resume = ctx.latest_checkpoint()          # (step, folder) or None
            ...
            with ctx.checkpoint(step) as folder:      # written to a temp folder, renamed when complete
                save_state(folder)
            ...
            (ctx.out_dir / "model.pt").write_bytes(...)   # outputs; published atomically after run()

`run` must be deterministic given params, inputs and the recorded seeds: a killed run, rerun, resumes
from the newest checkpoint and publishes the same result as an uninterrupted one.
"""
from __future__ import annotations

import dataclasses
import logging
from abc import ABC, abstractmethod
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Protocol

from pipeline.errors import UserError


@dataclass(frozen=True)
class Resources:
    """Scheduling hints; executors use them to size process pools and Ray tasks (Ray reserves them on one
    node: num_cpus, num_gpus, memory)."""

    cpus: int = 1
    gpus: float = 0.0
    memory_gb: float = 2.0

    def describe(self) -> str:
        gpus = f"{self.gpus:g} GPU{'s' if self.gpus != 1 else ''}"
        return f"{self.cpus} CPU{'s' if self.cpus != 1 else ''}, {gpus}, {self.memory_gb:g} GB memory"


class Progress(Protocol):
    def update(self, n: int = 1, **metrics: float) -> None: ...


class StageContext(Protocol):
    """What a running stage can use. Implemented by the engine (`pipeline.engine`)."""

    key: str
    params: Any                 # an instance of the stage's Params dataclass
    inputs: dict[str, Path]     # upstream result folders and external paths, by declared name
    out_dir: Path               # empty temp folder; everything written here is published atomically
    scratch_dir: Path           # persists across attempts of this key (kept until gc); not published
    log: logging.Logger         # also written to the step's log file
    threads: int                # CPU threads this step may use (the stage applies it, e.g. torch)

    def latest_checkpoint(self) -> tuple[int, Path] | None:
        """The newest intact in-stage checkpoint: (step, folder), or None on a fresh start. Its files
        match the checksums written with it; a damaged newer one is reported and moved aside."""

    def checkpoint(self, step: int) -> AbstractContextManager[Path]:
        """A temp folder to fill; on clean exit it becomes the checkpoint for `step`, atomically.
        Older checkpoints beyond the newest two are deleted."""

    def progress(self, total: int, desc: str, initial: int = 0) -> AbstractContextManager[Progress]:
        """A progress bar with ETA (quiet mode: periodic log lines only)."""

    def record(self, **entries: Any) -> None:
        """Extra JSON-serialisable facts for the manifest: seeds, encoder identity, simulator flags."""


class Stage(ABC):
    name: ClassVar[str]
    version: ClassVar[str]
    Params: ClassVar[type]
    upstream: ClassVar[tuple[str, ...]] = ()
    external: ClassVar[tuple[str, ...]] = ()
    resources: ClassVar[Resources] = Resources()
    nonsemantic_params: ClassVar[frozenset[str]] = frozenset()
    packages: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def resources_for(cls, params: Any) -> Resources:
        """The hints for one step, from its params: `resources`, with one GPU when the step runs on CUDA
        (a `device` param of "cuda" or "cuda:N") and the stage declared none, and `num_threads` CPUs when
        that param is set (> 0). Override for other rules."""
        hints = cls.resources
        device = str(getattr(params, "device", "") or "")
        if device.startswith("cuda") and hints.gpus <= 0:
            hints = dataclasses.replace(hints, gpus=1.0)
        threads = getattr(params, "num_threads", 0)
        if isinstance(threads, int) and not isinstance(threads, bool) and threads > 0:
            hints = dataclasses.replace(hints, cpus=threads)
        return hints

    @abstractmethod
    def run(self, ctx: StageContext) -> None:
        """Compute the result into `ctx.out_dir`."""

    @classmethod
    def runtime_environment(cls, params: Any) -> dict[str, Any]:
        """Facts of the computing process that change this stage's bits (e.g. the numerical code paths
        its CPU takes); they enter the key, and a worker whose own differ refuses to compute it. Plain
        JSON; cheap after the first call."""
        return {}

    @classmethod
    def provenance(cls) -> dict[str, Any]:
        """Facts recorded in the manifest but not keyed (machine model, threads in use)."""
        return {}


class ParamsError(UserError):
    """A user-facing parameter problem (unknown key, wrong type); the CLI prints it and exits 2.
    A `UserError`, hence still a ValueError."""


def build_params(params_cls: type, values: dict[str, Any], where: str) -> Any:
    """Validate a plain dict against a frozen params dataclass; `where` names the source for errors."""
    fields = {f.name: f for f in dataclasses.fields(params_cls)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise ParamsError(
            f"{where}: unknown parameter(s) {', '.join(unknown)}; "
            f"known parameters are: {', '.join(sorted(fields))}."
        )
    converted = {}
    for key, value in values.items():
        converted[key] = _coerce(value, fields[key], where)
    return params_cls(**converted)


_SIMPLE_TYPES = {"int": int, "float": float, "str": str, "bool": bool}


def _coerce(value: Any, field: dataclasses.Field, where: str) -> Any:
    type_name = field.type if isinstance(field.type, str) else getattr(field.type, "__name__", "")
    expected = _SIMPLE_TYPES.get(type_name)
    if expected is None:
        return value
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if expected is not bool and isinstance(value, bool) or not isinstance(value, expected):
        raise ParamsError(
            f"{where}: parameter '{field.name}' must be {type_name}, got {type(value).__name__} {value!r}."
        )
    return value
