"""Workflow TOML -> steps: grid expansion, shared upstream steps, overrides and user errors."""
from pathlib import Path

import pytest

from experiments.workflow import WorkflowError, load_workflow
from pipeline.dag import External

ROOT = Path(__file__).resolve().parents[1]
ABLATION = ROOT / "workflows" / "ablation.toml"


def test_ablation_expands_to_the_paper_grid_with_shared_upstream_steps():
    wf = load_workflow(ABLATION, ["scenes_dir=/nonexistent"])
    toggles = [c.method.flags for c in wf.cells[1:] if c.seed == 0]
    assert sorted({c.seed for c in wf.cells[1:]}) == [0, 1, 2]           # three seeds by default
    # Table 2 of the paper, in its row order.
    assert toggles == [(False, False, False), (True, False, False), (True, True, False),
                       (False, False, True), (True, False, True), (True, True, True)]
    assert wf.cells[0].is_original and "edit" not in wf.cells[0].evaluate.inputs
    fits = {id(c.evaluate.inputs["fit"]) for c in wf.cells}
    datasets = {id(c.evaluate.inputs["dataset"]) for c in wf.cells}
    assert len(fits) == 1 and len(datasets) == 1, "preprocess and fit must be one step for the whole grid"
    assert wf.instruction == "Make it look like it just snowed"
    assert wf.scene_origin == "procedural"
    edit_params = wf.cells[-1].edit.params
    assert edit_params["instruction"] == wf.instruction and edit_params["edit_id"] == "snow"


def test_seeds_axis_multiplies_edit_cells_only():
    wf = load_workflow(ABLATION, ["scenes_dir=/nonexistent", "seeds=[0, 1, 2]"])
    assert len(wf.cells) == 1 + 6 * 3
    assert sorted({c.seed for c in wf.cells[1:]}) == [0, 1, 2]
    assert len([s for s in wf.steps if s.stage == "fit"]) == 1


def test_stage_overrides_reach_the_step_params():
    wf = load_workflow(ABLATION, ["scenes_dir=/nonexistent", "fit.iterations=123", "edit.editor=ip2p",
                                  "edit=blue_tent"])
    fit = next(s for s in wf.steps if s.stage == "fit")
    assert fit.params["iterations"] == 123
    assert all(c.edit.params["editor"] == "ip2p" for c in wf.cells[1:])
    assert wf.instruction == "Turn the tent blue"


def test_user_folder_takes_precedence_over_procedural_scene(tmp_path):
    folder = tmp_path / "campsite"
    (folder / "images").mkdir(parents=True)
    (folder / "scene.toml").write_text(
        '[scene]\nname = "campsite"\n[[edits]]\nid = "snow"\ninstruction = "Make it snow"\n'
        'source_caption = "a real campsite"\ntarget_caption = "a snowy real campsite"\n')
    wf = load_workflow(ABLATION, [f"scenes_dir={tmp_path}"])
    assert wf.scene_origin.startswith("user folder")
    preprocess = next(s for s in wf.steps if s.stage == "preprocess")
    assert isinstance(preprocess.inputs["source"], External)
    assert wf.instruction == "Make it snow"


@pytest.mark.parametrize("override, fragment", [
    ("scene=atlantis", "unknown scene 'atlantis'"),
    ("fitt.iterations=3", "unknown stage 'fitt'"),
    ("colour=red", "unknown key 'colour'"),
    ("edit=melt", "not in scene 'campsite'"),
    ("variants=[[true, false]]", "three booleans"),
])
def test_bad_overrides_are_user_errors_naming_the_problem(override, fragment):
    with pytest.raises(WorkflowError, match=fragment):
        load_workflow(ABLATION, ["scenes_dir=/nonexistent", override])


def test_bad_toml_names_file_and_line(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[workflow]\nscene = "tiny"\nseeds = [0,\n')
    with pytest.raises(WorkflowError, match=r"bad\.toml.*line"):
        load_workflow(bad)


@pytest.mark.parametrize("workflow", sorted((ROOT / "workflows").glob("*.toml")), ids=lambda p: p.name)
def test_every_shipped_workflow_expands_and_its_params_validate(workflow, tmp_path):
    """Keying builds every step's frozen params dataclass, so a mistyped or unknown stage parameter in a
    shipped workflow fails here instead of minutes into a user's run."""
    from pipeline.dag import compute_keys
    from pipeline.store import Store
    from stages import STAGES

    wf = load_workflow(workflow, ["scenes_dir=/nonexistent"])
    keyed = compute_keys(wf.steps, registry=STAGES, store=Store(tmp_path / "cache"))
    stages = {step.stage for step in keyed}
    # Every workflow with edited rows runs the edit stage; workflows/reconstruct.toml (methods = []) has none.
    edited = {"edit"} if any(c.method.flags for c in wf.cells) else set()
    assert {"scene", "preprocess", "fit", "evaluate"} | edited <= stages <= set(STAGES)
    assert ("perframe" in stages) == any(c.label == "per-frame" for c in wf.cells)
    assert len([s for s in keyed if s.stage == "fit"]) == len(wf.scenes)
    if dict(wf.axes)["edit"] == 1 and len(wf.axes) == 4:       # one scene edit, no parameter axes
        assert len(wf.cells) == 1 + len(wf.settings["methods"]) * len(wf.settings.get("seeds", [0]))
