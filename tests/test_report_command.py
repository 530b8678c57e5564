"""`report_workflow`: a workflow's cells are looked up in the store by key and become report rows.
Stand-in edit/evaluate stages keep this independent of model training; the store and keys are real."""
import json
from dataclasses import dataclass
from pathlib import Path

import pytest

from experiments.commands.report import report_workflow, workflow_rows
from experiments.methods import ORIGINAL, Method
from experiments.report import ReportError
from experiments.workflow import Cell, Workflow
from pipeline.dag import Step, compute_keys
from pipeline.stage import Stage
from pipeline.store import Store
from tests.test_report import make_edit, make_evaluate

REGISTRY = {"edit": "tests.test_report_command:StandInEdit",
            "evaluate": "tests.test_report_command:StandInEvaluate"}


@dataclass(frozen=True)
class EditParams:
    variant: str = ""
    seed: int = 0


@dataclass(frozen=True)
class EvaluateParams:
    variant: str = ""


class StandInEdit(Stage):
    name = "edit"
    version = "test"
    Params = EditParams

    def run(self, ctx):  # results are published by the test itself
        raise NotImplementedError


class StandInEvaluate(Stage):
    name = "evaluate"
    version = "test"
    Params = EvaluateParams
    upstream = ("edit",)

    def run(self, ctx):
        raise NotImplementedError


def _publish(store: Store, key: str, build) -> None:
    tmp = store.new_tmp(key)
    build(tmp / "x")
    for item in (tmp / "x").iterdir():
        item.rename(tmp / item.name)
    (tmp / "x").rmdir()
    store.publish(key, tmp, {"stage": "test"})


@pytest.fixture
def setup(tmp_path, monkeypatch):
    monkeypatch.setattr("stages.STAGES", REGISTRY)
    store = Store(tmp_path / "cache")
    original = Step("evaluate", {"variant": "original"}, label="evaluate[original]")
    cells = [Cell(ORIGINAL, original)]
    values = {"baseline": 0.1, "DF+SA+CCI": 0.2}
    for label, flag in (("baseline", False), ("DF+SA+CCI", True)):
        edit = Step("edit", {"variant": label, "seed": 0}, label=f"edit[{label}]")
        evaluate = Step("evaluate", {"variant": label}, {"edit": edit}, label=f"evaluate[{label}]")
        cells.append(Cell(Method.idu(flag, flag, flag, label=label), evaluate, 0, edit))
    steps = [original] + [s for c in cells[1:] for s in (c.edit, c.evaluate)]
    keys = compute_keys(steps, registry=REGISTRY, store=store)
    _publish(store, keys[original].key,
             lambda f: make_evaluate(f, {"clip_text_image_direction": 0.0}, (90, 140, 60), editor=None))
    for cell in cells[1:]:
        _publish(store, keys[cell.edit].key, lambda f: make_edit(f, 1.0))
    workflow = Workflow(name="t", path=Path("t.toml"), scene_name="tiny", scene_origin="procedural",
                        edit_id="snow", instruction="Make it snow", source_caption="a", target_caption="b",
                        steps=steps, cells=cells, report_dir=tmp_path / "reports")
    return workflow, store, keys, values


def test_rows_and_report_from_the_store(setup, tmp_path):
    workflow, store, keys, values = setup
    for cell in workflow.cells[1:]:
        _publish(store, keys[cell.evaluate].key,
                 lambda f, v=values[cell.label]: make_evaluate(f, {"clip_text_image_direction": v}, (200, 200, 200)))
    rows = workflow_rows(workflow, store)
    assert [r.label for r in rows] == ["Original scene", "baseline", "DF+SA+CCI"]
    assert rows[0].method.is_original and rows[0].method.flags is None and rows[0].edit_dir is None
    assert rows[2].method.dual_field is True and rows[1].method.consistency is False
    assert rows[1].evaluate_dir == store.object_path(keys[workflow.cells[1].evaluate].key)
    assert rows[1].edit_dir == store.object_path(keys[workflow.cells[1].edit].key)
    index = report_workflow(workflow, store)
    assert index == tmp_path / "reports" / "index.html"
    table = json.loads((tmp_path / "reports" / "table.json").read_text())
    t2i = [r["metrics"]["clip_text_image_direction"]["mean"] for r in table["rows"]]
    assert t2i == [0.0, 0.1, 0.2]
    assert (tmp_path / "reports" / "curves" / "loss.png").is_file()     # from the edit results
    assert "Make it snow" in index.read_text()


def test_missing_results_are_named(setup):
    workflow, store, _keys, _ = setup
    with pytest.raises(ReportError, match=r"evaluate\[baseline\], evaluate\[DF\+SA\+CCI\]"):
        workflow_rows(workflow, store)


def test_rows_carry_scene_edit_method_seed_and_axis_values(setup):
    """The report interface for grids: each row names its scene, edit, method label, seed and the
    parameter-axis values of its cell."""
    import dataclasses

    workflow, store, keys, values = setup
    for cell in workflow.cells[1:]:
        _publish(store, keys[cell.evaluate].key,
                 lambda f, v=values[cell.label]: make_evaluate(f, {"clip_text_image_direction": v}, (200, 200, 200)))
    workflow.cells = [dataclasses.replace(c, scene="tiny", edit_id="snow",
                                          params=() if c.is_original else (("w_max", 0.3),))
                      for c in workflow.cells]
    rows = workflow_rows(workflow, store)
    assert [(r.scene, r.edit, r.label, r.seed, r.params) for r in rows] == [
        ("tiny", "snow", "Original scene", None, ()), ("tiny", "snow", "baseline", 0, (("w_max", 0.3),)),
        ("tiny", "snow", "DF+SA+CCI", 0, (("w_max", 0.3),))]
    hash(rows[1])                            # rows stay frozen and hashable
