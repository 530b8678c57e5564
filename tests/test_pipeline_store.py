"""The store and the runner in one process: publish, reuse, corruption, gc, failures, run records."""
from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.context import StepContext
from pipeline.dag import External, Step, dry_run
from pipeline.executors import SerialExecutor
from pipeline.runner import run_steps
from pipeline.store import MANIFEST, Store
from tests.pipeline_stages import REGISTRY

ROOT = Path(__file__).resolve().parents[1]


def run(steps, store, run_dir):
    return run_steps(steps, registry=REGISTRY, store=store, executor=SerialExecutor(threads=1),
                     run_dir=run_dir, quiet=True)


def executions(trace: Path) -> int:
    """How many times the count stage started from scratch (its first step writes '<pid> 1')."""
    return sum(1 for line in trace.read_text().splitlines() if line.split()[1] == "1") if trace.exists() else 0


def tree_digest(folder: Path) -> dict[str, str]:
    """sha256 of every file below `folder` except the manifest (which holds timings)."""
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.name != MANIFEST}


def test_publish_then_reuse_with_manifest(tmp_path):
    store, trace = Store(tmp_path / "cache"), tmp_path / "trace"
    a = Step("count", {"n": 6, "trace": str(trace)}, label="a")
    b = Step("add", {"value": 0.5}, {"left": a}, label="b")
    first = run([b], store, tmp_path / "runs" / "r1")
    assert first.ok and first.status == {a: "done", b: "done"}
    assert (first.results[a] / "total.txt").read_text() == f"{sum(range(6))}\n"
    assert float((first.results[b] / "total.txt").read_text()) == sum(range(6)) + 0.5
    manifest = json.loads((first.results[a] / MANIFEST).read_text())
    assert manifest["files"]["sub/steps.txt"] == {"size": 2, "sha256": hashlib.sha256(b"6\n").hexdigest()}
    assert manifest["record"] == {"counted": 6} and manifest["key_inputs"]["params"] == {"n": 6, "start": 0}
    assert not store.scratch_path(manifest["key"]).exists()          # checkpoints dropped after publish
    second = run([b], store, tmp_path / "runs" / "r2")
    assert second.status == {a: "cached", b: "cached"} and executions(trace) == 1
    assert second.results == first.results
    record = json.loads((tmp_path / "runs" / "r2" / "run.json").read_text())
    assert [s["status"] for s in record["steps"]] == ["cached", "cached"] and record["status"] == "done"
    assert record["steps"][1]["inputs"]["left"]["key"] == manifest["key"]


def test_corrupted_output_is_quarantined_and_recomputed(tmp_path, caplog):
    store, trace = Store(tmp_path / "cache"), tmp_path / "trace"
    a = Step("count", {"n": 5, "trace": str(trace)}, label="a")
    path = run([a], store, tmp_path / "runs" / "r1").results[a]
    good = tree_digest(path)
    victim = path / "sub" / "steps.txt"
    data = bytearray(victim.read_bytes())
    data[0] ^= 0x01                                                   # flip one bit, same size
    victim.write_bytes(bytes(data))
    assert any("content changed" in p for p in store.problems(path.name))
    with caplog.at_level(logging.WARNING, logger="pipeline.store"):
        again = run([a], store, tmp_path / "runs" / "r2")
    assert again.status[a] == "done" and executions(trace) == 2      # recomputed, not reused
    assert "steps.txt" in caplog.text and "damaged" in caplog.text   # the warning names the file
    assert tree_digest(again.results[a]) == good
    quarantined = [p for p in (store.root / "quarantine").iterdir() if p.is_dir()]
    assert len(quarantined) == 1 and (quarantined[0] / "sub" / "steps.txt").read_bytes() == bytes(data)


def test_truncated_and_extra_files_are_detected(tmp_path):
    store = Store(tmp_path / "cache")
    a = Step("count", {"n": 3})
    path = run([a], store, tmp_path / "runs" / "r").results[a]
    (path / "total.txt").write_text("")
    (path / "stray.bin").write_bytes(b"x")
    problems = " ".join(store.problems(path.name, full=False))
    assert "total.txt: size 0" in problems and "stray.bin: not listed" in problems
    assert store.lookup(path.name) is None and not path.exists()


def test_user_input_folder_is_not_modified(tmp_path):
    source = tmp_path / "user_images"
    source.mkdir()
    for i in range(5):
        (source / f"{i:04d}.png").write_bytes(os.urandom(1000 + i))
    before = tree_digest(source)
    mtimes = {p.name: p.stat().st_mtime_ns for p in source.iterdir()}
    step = Step("digest", {"scale": 2}, {"source": External(source)})
    result = run([step], Store(tmp_path / "cache"), tmp_path / "runs" / "r")
    assert int((result.results[step] / "total.txt").read_text()) == 2 * sum(1000 + i for i in range(5))
    assert tree_digest(source) == before
    assert {p.name: p.stat().st_mtime_ns for p in source.iterdir()} == mtimes


def test_stage_modifying_its_input_is_refused(tmp_path):
    source = tmp_path / "user.txt"
    source.write_text("original")
    step = Step("vandal", {}, {"source": External(source)}, label="vandal")
    store = Store(tmp_path / "cache")
    result = run([step], store, tmp_path / "runs" / "r")
    assert result.status[step] == "failed" and result.failed[0].user_error
    assert "input 'source'" in result.failed[0].error and "changed while step 'vandal' ran" in result.failed[0].error
    assert not list(store.entries())


def test_failure_skips_dependants_but_not_independent_steps(tmp_path):
    store = Store(tmp_path / "cache")
    base = Step("count", {"n": 2}, label="base")
    bad = Step("fail", {"message": "scene folder has no images"}, {"left": base}, label="bad")
    after_bad = Step("add", {}, {"left": bad}, label="after-bad")
    independent = Step("count", {"n": 4}, label="independent")
    boom = Step("fail", {"internal": True, "message": "kaboom"}, label="boom")
    result = run([after_bad, independent, boom], store, tmp_path / "runs" / "r")
    assert result.status == {base: "done", bad: "failed", after_bad: "skipped", independent: "done",
                             boom: "failed"}
    by_label = {f.label: f for f in result.failed}
    assert by_label["bad"].user_error and "scene folder has no images" in by_label["bad"].error
    assert not by_label["boom"].user_error and "RuntimeError: kaboom" in by_label["boom"].error
    assert by_label["after-bad"].skipped
    log_text = by_label["boom"].log_path.read_text()
    assert "Traceback" in log_text and "kaboom" in log_text
    record = json.loads((tmp_path / "runs" / "r" / "run.json").read_text())
    statuses = {s["label"]: (s["status"], s["error"]) for s in record["steps"]}
    assert statuses["after-bad"][0] == "skipped" and "BadInputError" in statuses["bad"][1]
    assert record["status"] == "failed"
    summary = result.summary().splitlines()
    assert summary[0] == "2 done, 2 failed, 1 skipped"
    assert any(line.startswith("  FAILED boom: RuntimeError: kaboom (log: ") for line in summary)
    assert not list((store.root / "tmp").iterdir())                  # failed attempts leave no tmp


def test_gc_keeps_reachable_and_pinned_and_verify_reports_damage(tmp_path):
    store, runs = Store(tmp_path / "cache"), tmp_path / "runs"
    kept_up = Step("count", {"n": 2}, label="kept-up")
    kept = Step("add", {"value": 1.0}, {"left": kept_up}, label="kept")
    dropped = Step("count", {"n": 3}, label="dropped")
    pinned_up = Step("count", {"n": 4}, label="pinned-up")
    pinned = Step("add", {"value": 2.0}, {"left": pinned_up}, label="pinned")
    r1 = run([kept], store, runs / "keep")
    elsewhere = Step("count", {"n": 7}, label="elsewhere")
    r0 = run([elsewhere], store, tmp_path / "other-runs" / "x")   # not under --runs: found by registration
    r2 = run([dropped, pinned], store, runs / "gone")
    (runs / "gone" / "run.json").unlink()                   # that run record is deleted
    store.pin(r2.results[pinned].name)                       # ... but one result is pinned
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    cli = [sys.executable, "-m", "experiments.cli", "--cache", str(store.root), "--runs", str(runs)]
    out = subprocess.run(cli + ["cache", "gc"], check=False, capture_output=True, text=True, env=env, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    remaining = {k for k, _ in store.entries()}
    assert remaining == {r1.results[kept].name, r1.results[kept_up].name, r2.results[pinned].name,
                         r2.results[pinned_up].name, r0.results[elsewhere].name}  # pin keeps its upstream too
    assert r2.results[dropped].name[:12] in out.stdout
    ls = subprocess.run(cli + ["cache", "ls"], check=False, capture_output=True, text=True, env=env)
    assert ls.returncode == 0 and "5 entries" in ls.stdout and "n=4" in ls.stdout
    (r1.results[kept] / "total.txt").write_text("3.5\n")        # same size, other content
    verify = subprocess.run(cli + ["cache", "verify"], check=False, capture_output=True, text=True, env=env)
    assert verify.returncode == 1
    assert f"DAMAGED {r1.results[kept].name[:12]}" in verify.stdout and "total.txt" in verify.stdout
    assert "4 intact, 1 damaged" in verify.stdout
    # with no run record and no pin at all, gc refuses to empty the store unless told to
    shutil.rmtree(runs)
    shutil.rmtree(tmp_path / "other-runs")
    store.unpin(r2.results[pinned].name)
    refused = subprocess.run(cli + ["cache", "gc"], check=False, capture_output=True, text=True, env=env)
    assert refused.returncode == 2 and "--force" in refused.stderr and len(list(store.entries())) == 5
    forced = subprocess.run(cli + ["cache", "gc", "--force"], check=False, capture_output=True, text=True, env=env)
    assert forced.returncode == 0 and not list(store.entries())


def test_dry_run_states(tmp_path):
    store = Store(tmp_path / "cache")
    done = Step("count", {"n": 2}, label="done")
    partial = Step("count", {"n": 9}, label="partial")
    run([done], store, tmp_path / "runs" / "r")
    keyed_partial = dry_run([partial], registry=REGISTRY, store=store)[0]
    scratch = next(iter(store.scratch.glob(f"{keyed_partial[1]}*")), None)
    assert scratch is None and keyed_partial[2] == "pending"
    from pipeline.dag import compute_keys

    key = compute_keys([partial], registry=REGISTRY, store=store)[partial].key
    ctx = StepContext(key=key, params=None, inputs={}, out_dir=tmp_path / "o", scratch_dir=store.scratch_path(key),
                      log=logging.getLogger("t"))
    with ctx.checkpoint(3) as folder:
        (folder / "state.json").write_text('{"total": 3}')
    assert [(label, state) for label, _, state in dry_run([done, partial], registry=REGISTRY, store=store)] == \
        [("done", "cached"), ("partial", "partial")]
    resumed = run([partial], store, tmp_path / "runs" / "r2")
    assert (resumed.results[partial] / "total.txt").read_text() == f"{sum(range(9))}\n"
    manifest = json.loads((resumed.results[partial] / MANIFEST).read_text())
    assert manifest["resumed_from_checkpoint"] == 3


def test_checkpoints_keep_newest_two_and_ignore_partial_writes(tmp_path):
    ctx = StepContext(key="k", params=None, inputs={}, out_dir=tmp_path / "o", scratch_dir=tmp_path / "s",
                      log=logging.getLogger("t"))
    assert ctx.latest_checkpoint() is None
    for step in (1, 2, 3):
        with ctx.checkpoint(step) as folder:
            (folder / "x").write_text(str(step))
    with pytest.raises(RuntimeError), ctx.checkpoint(4) as folder:
        (folder / "x").write_text("half")
        raise RuntimeError("killed while writing")
    step, folder = ctx.latest_checkpoint()
    assert step == 3 and (folder / "x").read_text() == "3"
    assert sorted(p.name for p in (tmp_path / "s" / "checkpoints").iterdir()) == ["000000000002", "000000000003"]
    with pytest.raises(TypeError, match="seed"):
        ctx.record(seed=object())
