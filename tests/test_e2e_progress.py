"""What a run prints while steps make progress: one step at a time gets a tqdm bar; when several steps
can be in flight (a pool with more than one slot, Ray) each step reports a log line every ~10% instead,
since bars redrawn by several processes on one terminal line overwrite each other; --quiet always
gives the log lines."""
from __future__ import annotations

import pytest

from pipeline.dag import Step
from pipeline.executors import SerialExecutor
from pipeline.runner import run_steps
from pipeline.store import Store
from tests.pipeline_stages import REGISTRY


class RecordingExecutor(SerialExecutor):
    """Runs jobs serially but announces `slots` parallel slots, and keeps the jobs it was given."""

    def __init__(self, slots: int):
        super().__init__(threads=1)
        self.slots = slots
        self.jobs = []

    def submit(self, job, resources):
        self.jobs.append(job)
        return super().submit(job, resources)


@pytest.mark.parametrize("slots, quiet, expect_bar", [(1, False, True), (2, False, False), (1, True, False)])
def test_progress_bar_only_when_one_step_runs_at_a_time(tmp_path, capfd, slots, quiet, expect_bar):
    executor = RecordingExecutor(slots)
    step = Step("count", {"n": 10}, label="c")
    result = run_steps([step], registry=REGISTRY, store=Store(tmp_path / "cache"), executor=executor,
                       run_dir=tmp_path / "runs" / "r", quiet=quiet)
    assert result.ok
    assert [job.quiet for job in executor.jobs] == [not expect_bar]
    err = capfd.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("[c] counting: ")]
    if expect_bar:
        assert "c: counting: 100%" in err and "\r" in err     # tqdm redraws its line
        assert lines == []
    else:
        assert "\r" not in err
        assert lines[0].startswith("[c] counting: 1/10 (10%)") and lines[-1].startswith("[c] counting: 10/10 (100%)")
        assert len(lines) == 10
