"""Every shipped workflow keeps its step keys, labels and cells across the layout move and the
expander's rewrite (issue 31): tests/data/workflow_keys.json was recorded by tests/workflow_key_record.py
from the expander before the move, and the current one must reproduce it step for step."""
import json

import pytest

from tests.workflow_key_record import CASES, DATA, NO_USER, ROOT, case_id, describe, stage_fingerprints

RECORDED = json.loads(DATA.read_text())


@pytest.mark.parametrize("workflow, overrides", CASES, ids=[case_id(w, o) for w, o in CASES])
def test_workflow_expands_to_the_recorded_steps(workflow, overrides):
    from experiments.workflow import load_workflow

    recorded = RECORDED["cases"][case_id(workflow, overrides)]
    now = describe(load_workflow(ROOT / "workflows" / f"{workflow}.toml", [NO_USER, *overrides]))
    same_stages = stage_fingerprints() == RECORDED["stages"]
    if not same_stages:           # a stage's version, defaults or packages changed since the recording
        for part in ("steps", "cells"):
            recorded[part] = [row[:-1] for row in recorded[part]]
            now[part] = [row[:-1] for row in now[part]]
    now = json.loads(json.dumps(now))          # tuples -> lists, as recorded
    assert now["steps"] == recorded["steps"]   # stage, label, shape (and key) of every step
    assert now["cells"] == recorded["cells"]   # the report rows in order: label, seed, scene, edit, axes


def test_the_recording_covers_every_shipped_workflow():
    shipped = {p.stem for p in (ROOT / "workflows").glob("*.toml")}
    assert shipped <= {w for w, _ in CASES}
