"""Process-pool and Ray executors give the same results as serial on a small DAG."""
from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.dag import External, Step
from pipeline.executors import ProcessPoolExecutor, SerialExecutor, cpu_count
from pipeline.runner import run_steps
from pipeline.stage import Resources
from pipeline.store import Store
from tests.pipeline_stages import REGISTRY
from tests.test_pipeline_store import tree_digest


def small_dag(tmp_path: Path, threads_file: Path) -> list[Step]:
    source = tmp_path / "source"
    source.mkdir(exist_ok=True)
    (source / "a.txt").write_text("hello")
    (source / "b.txt").write_text("world!")
    digest = Step("digest", {"scale": 3}, {"source": External(source)}, label="digest")
    counts = [Step("count", {"n": n}, label=f"count{n}") for n in (3, 4, 5)]
    left = Step("add", {"value": 1.5, "threads_seen": str(threads_file)}, {"left": counts[0], "right": counts[1]},
                label="left")
    right = Step("add", {"value": -2.0}, {"left": counts[2], "right": digest}, label="right")
    top = Step("add", {}, {"left": left, "right": right}, label="top")
    duplicate = Step("count", {"n": 4}, label="count4-again")    # same key as counts[1]: computed once
    bad = Step("fail", {}, {"left": counts[0]}, label="bad")
    return [top, duplicate, bad]


def outputs(result) -> dict[str, tuple[str, dict]]:
    return {step.label: (result.status[step], tree_digest(path) if path else None)
            for step, path in ((s, result.results.get(s)) for s in result.status)}


def run_with(executor, tmp_path: Path, name: str):
    steps = small_dag(tmp_path, tmp_path / f"threads-{name}")
    store = Store(tmp_path / f"cache-{name}")
    return run_steps(steps, registry=REGISTRY, store=store, executor=executor, run_dir=tmp_path / "runs" / name,
                     quiet=True)


@pytest.fixture
def serial(tmp_path):
    return run_with(SerialExecutor(threads=1), tmp_path, "serial")


def check_same(serial, other):
    expected = outputs(serial)
    assert outputs(other) == expected
    assert expected["top"][0] == "done" and expected["bad"][0] == "failed" and expected["count4-again"][0] == "done"
    top = next(path for step, path in serial.results.items() if step.label == "top")
    # left = 1.5 + (0+1+2) + (0+1+2+3); right = -2 + (0+1+2+3+4) + 3 * len("hello" + "world!")
    assert float((top / "total.txt").read_text()) == (1.5 + 3 + 6) + (-2.0 + 10 + 3 * 11)
    assert sorted(p.name for p in serial.results.values()) == sorted(p.name for p in other.results.values())


@pytest.mark.slow
def test_process_pool_matches_serial(tmp_path, serial):
    pool = run_with(ProcessPoolExecutor(jobs=2), tmp_path, "pool")
    check_same(serial, pool)
    # the add stage's CPU hint (1) or its share of the cores, whichever is larger
    assert (tmp_path / "threads-pool").read_text() == str(max(1, cpu_count() // 2))


def test_a_job_gets_its_hint_or_its_share_of_the_cores_capped_at_the_cores():
    pool = ProcessPoolExecutor.__new__(ProcessPoolExecutor)       # threads_for only: no worker processes
    pool.cores, pool.threads = 2, 1                               # two jobs on two cores
    assert pool.threads_for(Resources(cpus=1)) == 1
    assert pool.threads_for(Resources(cpus=2)) == 2
    assert pool.threads_for(Resources(cpus=16)) == 2
    pool.cores, pool.threads = 8, 4                               # two jobs on eight cores
    assert pool.threads_for(Resources(cpus=1)) == 4
    assert pool.threads_for(Resources(cpus=6)) == 6
    pool.cores, pool.threads = 2, 2                               # --jobs 1: the lone step gets the machine
    assert pool.threads_for(Resources(cpus=1)) == 2
    assert SerialExecutor(threads=4).threads_for(Resources(cpus=2)) == 2


@pytest.mark.slow
def test_threads_follow_the_schedule_and_the_result_does_not(tmp_path):
    # --jobs 1 gives each step every core, --jobs 2 splits them; the bytes are the same either way.
    seen = {name: tmp_path / f"threads-{name}" for name in ("a", "b", "c")}
    a = Step("add", {"value": 1.0, "threads_seen": str(seen["a"])}, label="a")
    b = Step("add", {"value": 2.0, "threads_seen": str(seen["b"])}, label="b")
    c = Step("wide_add", {"value": 3.0, "threads_seen": str(seen["c"])}, {"left": a, "right": b}, label="c")
    for jobs in (1, 2):
        for path in seen.values():
            path.unlink(missing_ok=True)
        result = run_steps([c], registry=REGISTRY, store=Store(tmp_path / f"cache-{jobs}"),
                           executor=ProcessPoolExecutor(jobs=jobs), run_dir=tmp_path / "runs" / str(jobs), quiet=True)
        assert (result.results[c] / "total.txt").read_text() == "6.0\n"
        share = max(1, cpu_count() // jobs)
        assert seen["a"].read_text() == seen["b"].read_text() == str(share)
        assert seen["c"].read_text() == str(max(min(2, cpu_count()), share))


@pytest.mark.slow
def test_process_pool_survives_a_killed_worker(tmp_path):
    killer = Step("suicide", {}, label="killer")
    after = Step("count", {"n": 3}, label="after")
    result = run_steps([killer, after], registry=REGISTRY, store=Store(tmp_path / "cache"),
                       executor=ProcessPoolExecutor(jobs=1), run_dir=tmp_path / "runs" / "r", quiet=True)
    assert result.status == {killer: "failed", after: "done"}
    assert "worker process died" in result.failed[0].error
    assert (result.results[after] / "total.txt").read_text() == "3\n"


@pytest.mark.slow
def test_ray_matches_serial(tmp_path, serial):
    ray = pytest.importorskip("ray")
    from pipeline.executors import RayExecutor

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        result = run_with(RayExecutor(), tmp_path, "ray")
    finally:
        ray.shutdown()
    check_same(serial, result)
