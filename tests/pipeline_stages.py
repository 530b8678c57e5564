"""Test-only stages for the engine tests, and a driver that runs a DAG in a real subprocess.

    python -m tests.pipeline_stages SPEC.json      runs the steps in SPEC and prints the result JSON

SPEC = {"cache": dir, "run_dir": dir, "executor": "serial"|"process"|"ray", "jobs": n,
        "die": null | "before_publish" | "mid_manifest", "lease_ttl_s": s (default 30),
        "clock_offset_s": s (this process's wall clock runs that far ahead, as on a host with a skewed clock),
        "steps": [{"stage", "params", "label", "inputs": {name: step index | {"external": path}}}]}
"""
from __future__ import annotations

import dataclasses
import json
import os
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from pipeline.stage import Resources, Stage

REGISTRY = {
    "count": "tests.pipeline_stages:CountStage",
    "add": "tests.pipeline_stages:AddStage",
    "wide_add": "tests.pipeline_stages:WideAddStage",
    "digest": "tests.pipeline_stages:DigestStage",
    "fail": "tests.pipeline_stages:FailStage",
    "vandal": "tests.pipeline_stages:VandalStage",
    "suicide": "tests.pipeline_stages:SuicideStage",
    "device_probe": "tests.pipeline_stages:DeviceProbeStage",
}


def _append(path: str, line: str) -> None:
    if path:
        with open(path, "a", encoding="utf-8") as f:
            f.write(line + "\n")
            f.flush()
            os.fsync(f.fileno())


@dataclass(frozen=True)
class CountParams:
    n: int = 10
    start: int = 0
    trace: str = ""           # non-semantic: file the stage appends "<pid> <i>" to at every step
    step_seconds: float = 0.0  # non-semantic: slows the stage so a test can interrupt it
    gate: str = ""            # non-semantic: at step 1 wait until this file exists
    native_sigterm: bool = False  # non-semantic: SIGTERM kills without unwinding, as after glog's handler
    checkpoint_trace: str = ""    # non-semantic: file the stage appends "<pid> checkpoint <i>" to after each one


class CountStage(Stage):
    """Counts from `start` to `n`, checkpointing the running total after every step."""

    name = "count"
    version = "1"
    Params = CountParams
    nonsemantic_params = frozenset({"trace", "step_seconds", "gate", "native_sigterm", "checkpoint_trace"})

    def run(self, ctx) -> None:
        p = ctx.params
        if p.native_sigterm:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
        i, total = 0, p.start
        resume = ctx.latest_checkpoint()
        if resume is not None:
            i, folder = resume
            total = json.loads((folder / "state.json").read_text())["total"]
            _append(p.trace, f"{os.getpid()} resume {i}")
        with ctx.progress(p.n, "counting", initial=i) as bar:
            while i < p.n:
                if i == 1 and p.gate:
                    while not Path(p.gate).exists():
                        time.sleep(0.01)
                total += i
                i += 1
                _append(p.trace, f"{os.getpid()} {i}")
                with ctx.checkpoint(i) as folder:
                    (folder / "state.json").write_text(json.dumps({"total": total}))
                _append(p.checkpoint_trace, f"{os.getpid()} checkpoint {i}")
                bar.update(1, total=total)
                if p.step_seconds:
                    time.sleep(p.step_seconds)
        ctx.record(counted=p.n)
        (ctx.out_dir / "total.txt").write_text(f"{total}\n")
        (ctx.out_dir / "sub").mkdir()
        (ctx.out_dir / "sub" / "steps.txt").write_text(f"{p.n}\n")


@dataclass(frozen=True)
class AddParams:
    value: float = 0.0
    threads_seen: str = ""    # non-semantic: file to write ctx.threads to


class AddStage(Stage):
    """total = value + the totals of whichever of `left` / `right` it was given (optional inputs)."""

    name = "add"
    version = "1"
    Params = AddParams
    upstream = ("left", "right")
    resources = Resources(cpus=1)
    nonsemantic_params = frozenset({"threads_seen"})

    def run(self, ctx) -> None:
        total = ctx.params.value
        for name in ("left", "right"):
            if name in ctx.inputs:
                total += float((ctx.inputs[name] / "total.txt").read_text())
        if ctx.params.threads_seen:
            Path(ctx.params.threads_seen).write_text(str(ctx.threads))
        (ctx.out_dir / "total.txt").write_text(f"{total!r}\n")


class WideAddStage(AddStage):
    """AddStage with a 2-CPU hint (the fit stage's)."""

    name = "wide_add"
    resources = Resources(cpus=2)


@dataclass(frozen=True)
class DigestParams:
    scale: int = 1


class DigestStage(Stage):
    """Reads an external file or folder and writes the byte count times `scale` (and a file listing)."""

    name = "digest"
    version = "1"
    Params = DigestParams
    external = ("source",)

    def run(self, ctx) -> None:
        source = ctx.inputs["source"]
        files = sorted(p for p in source.rglob("*") if p.is_file()) if source.is_dir() else [source]
        size = sum(p.stat().st_size for p in files)
        (ctx.out_dir / "total.txt").write_text(f"{size * ctx.params.scale}\n")
        (ctx.out_dir / "files.txt").write_text("".join(f"{p.name}\n" for p in files))


class BadInputError(ValueError):
    user_error = True


@dataclass(frozen=True)
class FailParams:
    message: str = "no good"
    internal: bool = False


class FailStage(Stage):
    name = "fail"
    version = "1"
    Params = FailParams
    upstream = ("left",)

    def run(self, ctx) -> None:
        if ctx.params.internal:
            raise RuntimeError(ctx.params.message)
        raise BadInputError(ctx.params.message)


class VandalStage(DigestStage):
    """A buggy stage that appends to the user's input file (the engine must refuse its result)."""

    name = "vandal"

    def run(self, ctx) -> None:
        super().run(ctx)
        with open(ctx.inputs["source"], "ab") as f:
            f.write(b"!")


class SuicideStage(FailStage):
    """Kills its own process with SIGKILL, like the out-of-memory killer would."""

    name = "suicide"

    def run(self, ctx) -> None:
        os.kill(os.getpid(), signal.SIGKILL)


@dataclass(frozen=True)
class DeviceProbeParams:
    device: str = "cpu"
    num_threads: int = 0
    gpus: float = 0.0              # > 0: ask for this many GPUs whatever the device
    tag: str = ""


class DeviceProbeStage(Stage):
    """A stage stub for placement tests: writes what it was given where it ran (CUDA_VISIBLE_DEVICES, the
    GPU ids and resources Ray assigned, its node and that node's resources)."""

    name = "device_probe"
    version = "1"
    Params = DeviceProbeParams
    resources = Resources(cpus=1, gpus=0, memory_gb=1.5)

    @classmethod
    def resources_for(cls, params) -> Resources:
        hints = super().resources_for(params)
        return dataclasses.replace(hints, gpus=params.gpus) if params.gpus > 0 else hints

    def run(self, ctx) -> None:
        seen = {"cuda_visible_devices": os.environ.get("CUDA_VISIBLE_DEVICES"), "threads": ctx.threads}
        try:
            import ray

            if ray.is_initialized():
                context = ray.get_runtime_context()
                node = next(n for n in ray.nodes() if n["NodeID"] == context.get_node_id())
                seen.update(gpu_ids=[str(g) for g in ray.get_gpu_ids()], node_id=context.get_node_id(),
                            node_resources=node["Resources"], assigned=context.get_assigned_resources())
        except ImportError:
            pass
        (ctx.out_dir / "seen.json").write_text(json.dumps(seen, sort_keys=True))


def build_steps(spec_steps: list[dict]):
    from pipeline.dag import External, Step

    steps: list[Step] = []
    for entry in spec_steps:
        inputs = {}
        for name, source in entry.get("inputs", {}).items():
            inputs[name] = External(source["external"]) if isinstance(source, dict) else steps[source]
        steps.append(Step(entry["stage"], entry.get("params", {}), inputs, entry.get("label", "")))
    return steps


def _die_at(where: str) -> None:
    """Make this process SIGKILL itself at a chosen point of publishing (crash-safety tests)."""
    from pipeline import store as store_module

    def kill_self(*args, **kwargs):
        if where == "mid_manifest":
            Path(args[0], store_module.MANIFEST).write_text('{"key": "trunc')   # half a manifest
        os.kill(os.getpid(), signal.SIGKILL)

    if where == "before_publish":
        store_module.Store._rename_into_place = staticmethod(kill_self)
    elif where == "mid_manifest":
        store_module._write_manifest = kill_self


def main(argv: list[str]) -> int:
    from pipeline.executors import make_executor
    from pipeline.runner import run_steps
    from pipeline.store import Store

    spec = json.loads(Path(argv[0]).read_text())
    if spec.get("clock_offset_s"):
        real_time, offset = time.time, float(spec["clock_offset_s"])
        time.time = lambda: real_time() + offset
    if spec.get("die"):
        _die_at(spec["die"])
    steps = build_steps(spec["steps"])
    executor = make_executor(spec.get("executor", "serial"), jobs=spec.get("jobs", 1),
                             address=spec.get("ray_address"))
    store = Store(spec["cache"], lease_ttl_s=spec.get("lease_ttl_s", 30.0))
    result = run_steps(steps, registry=REGISTRY, store=store, executor=executor,
                       run_dir=Path(spec["run_dir"]), quiet=True)
    print(json.dumps({"results": [str(result.results.get(s)) for s in steps],
                      "status": [result.status[s] for s in steps],
                      "failed": [f.error for f in result.failed]}))
    return 0 if result.ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
