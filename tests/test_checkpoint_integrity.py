"""In-stage checkpoints carry checksums: a damaged newest checkpoint is reported by name, moved aside, and
the newest intact one is used; with none intact the step starts over, saying so."""
from __future__ import annotations

import logging
from pathlib import Path

import pytest

from pipeline.context import CHECKSUM_FILE, StepContext


def make_ctx(root: Path) -> StepContext:
    return StepContext(key="k", params=None, inputs={}, out_dir=root / "out", scratch_dir=root / "scratch",
                       log=logging.getLogger("test.checkpoints"))


def write(ctx: StepContext, step: int, payload: bytes) -> Path:
    with ctx.checkpoint(step) as folder:
        (folder / "state.bin").write_bytes(payload)
        (folder / "sub").mkdir()
        (folder / "sub" / "meta.json").write_text(f'{{"step": {step}}}')
    return ctx.latest_checkpoint()[1]


def truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def flip_byte(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 3] ^= 0x01
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("damage", [truncate, flip_byte], ids=["truncated", "flipped byte"])
def test_damaged_newest_checkpoint_is_moved_aside_and_the_older_one_used(tmp_path, caplog, damage):
    ctx = make_ctx(tmp_path)
    write(ctx, 10, bytes(range(256)) * 40)
    newest = write(ctx, 20, bytes(range(255, -1, -1)) * 40)
    assert (newest / CHECKSUM_FILE).is_file()
    damage(newest / "state.bin")

    resumed = make_ctx(tmp_path)               # a rerun: a fresh context on the same scratch folder
    with caplog.at_level(logging.WARNING, logger="test.checkpoints"):
        step, folder = resumed.latest_checkpoint()
    assert step == 10 and (folder / "state.bin").read_bytes() == bytes(range(256)) * 40
    assert str(newest) in caplog.text and "state.bin" in caplog.text and "damaged" in caplog.text
    aside = [p for p in newest.parent.iterdir() if p.name.startswith("damaged-000000000020")]
    assert len(aside) == 1 and not newest.exists()
    assert str(aside[0]) in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="test.checkpoints"):
        assert resumed.latest_checkpoint()[0] == 10      # stays put; no further warnings
    assert caplog.text == ""


def test_every_checkpoint_damaged_starts_over_and_says_so(tmp_path, caplog):
    ctx = make_ctx(tmp_path)
    first = write(ctx, 1, b"a" * 1000)
    second = write(ctx, 2, b"b" * 1000)
    flip_byte(first / "state.bin")
    (second / "sub" / "meta.json").unlink()
    with caplog.at_level(logging.WARNING, logger="test.checkpoints"):
        assert make_ctx(tmp_path).latest_checkpoint() is None
    assert "sub/meta.json: missing" in caplog.text and "content changed" in caplog.text
    assert "starts over" in caplog.text
    assert not any(p.name.isdigit() for p in first.parent.iterdir())


def test_a_checkpoint_without_checksums_or_with_extra_files_is_not_trusted(tmp_path, caplog):
    ctx = make_ctx(tmp_path)
    folder = write(ctx, 5, b"x" * 100)
    (folder / "stray.bin").write_bytes(b"?")
    with caplog.at_level(logging.WARNING, logger="test.checkpoints"):
        assert make_ctx(tmp_path).latest_checkpoint() is None
    assert "stray.bin: not written with the checkpoint" in caplog.text
    legacy = make_ctx(tmp_path / "legacy")
    folder = write(legacy, 3, b"y")
    (folder / CHECKSUM_FILE).unlink()
    assert make_ctx(tmp_path / "legacy").latest_checkpoint() is None


@pytest.mark.slow
def test_fit_resumes_from_the_intact_checkpoint_when_the_newest_is_truncated(tiny_dataset, tmp_path, caplog):
    """The issue's case: a damaged newest fit checkpoint made every rerun fail inside torch.load."""
    import torch

    from stages.fit import FitParams, FitStage
    from tests.test_fit import KILL_PARAMS, _weights

    params = FitParams(**{**KILL_PARAMS, "iterations": 30})
    reference = StepContext(key="r", params=params, inputs={"dataset": tiny_dataset}, out_dir=tmp_path / "ref",
                            scratch_dir=tmp_path / "ref_scratch", log=logging.getLogger("test.fit"))
    FitStage().run(reference)
    # Checkpoints at 10 and 20 stay in the reference's scratch folder (the engine deletes them on publish).
    scratch = tmp_path / "ref_scratch"
    newest = max(p for p in (scratch / "checkpoints").iterdir() if p.name.isdigit())
    assert newest.name.endswith("20")
    truncate(newest / "trainer.pt")
    resumed = StepContext(key="r", params=params, inputs={"dataset": tiny_dataset}, out_dir=tmp_path / "again",
                          scratch_dir=scratch, log=logging.getLogger("test.fit"))
    with caplog.at_level(logging.INFO, logger="test.fit"):
        FitStage().run(resumed)
    assert "resumed from checkpoint at step 10" in caplog.text and str(newest) in caplog.text
    a, b = _weights(reference.out_dir), _weights(resumed.out_dir)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
