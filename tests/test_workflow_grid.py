"""Workflow grids: scenes x edits x methods x seeds x parameter axes, shipped grid workflows, list
overrides, filters, refusals before anything runs, and reruns that compute only new cells."""
import json
from pathlib import Path

import pytest

from experiments.workflow import WorkflowError, load_workflow

ROOT = Path(__file__).resolve().parents[1]
WORKFLOWS = ROOT / "workflows"
NO_USER = "scenes_dir=/nonexistent"


def _keyed(wf, tmp_path):
    from pipeline.dag import compute_keys
    from pipeline.store import Store
    from stages import STAGES

    return compute_keys(wf.steps, registry=STAGES, store=Store(tmp_path / "cache"))


def test_comparison_is_table1_over_every_library_scene_and_edit_but_tiny(tmp_path):
    from dualnerf.scenes.library import BUILDERS

    wf = load_workflow(WORKFLOWS / "comparison.toml", [NO_USER])
    expected = {(scene, e.id) for scene, (_, edits) in BUILDERS.items() if scene != "tiny" for e in edits}
    assert {(c.scene, c.edit_id) for c in wf.cells} == expected
    edited = [c for c in wf.cells if not c.is_original]
    assert len(edited) == len(expected) * 3 * 3
    assert {c.label for c in edited} == {"per-frame", "IN2N", "DualNeRF"}
    assert {c.seed for c in edited} == {0, 1, 2}
    assert len([c for c in wf.cells if c.label == "Original scene"]) == len(expected)
    keyed = _keyed(wf, tmp_path)
    scenes = {scene for scene, _ in expected}
    assert len([s for s in keyed if s.stage == "fit"]) == len(scenes), "one fit per scene"
    assert len([s for s in keyed if s.stage == "preprocess"]) == len(scenes)
    for cell in edited:
        if cell.label == "per-frame":
            assert cell.edit is None and cell.perframe.params["seed"] == cell.seed
            assert cell.evaluate.inputs["perframe"] is cell.perframe
            assert cell.perframe.inputs["gtviews"].params["edit_id"] == cell.edit_id
        else:
            toggles = cell.edit.params["dual_field"], cell.edit.params["annealing"], cell.edit.params["consistency"]
            assert toggles == ((True,) * 3 if cell.label == "DualNeRF" else (False,) * 3)
    assert wf.report_dir == Path("reports/comparison")


def test_comparison_shares_its_campsite_cells_with_the_ablation(tmp_path):
    comparison = load_workflow(WORKFLOWS / "comparison.toml", [NO_USER])
    ablation = load_workflow(WORKFLOWS / "ablation.toml", [NO_USER])
    keys_c = {k.key for k in _keyed(comparison, tmp_path).values()}
    keyed_a = _keyed(ablation, tmp_path)
    by_label = {c.label: keyed_a[c.evaluate].key for c in ablation.cells}
    assert by_label["baseline"] in keys_c and by_label["DF+SA+CCI"] in keys_c
    assert by_label["Original scene"] in keys_c


def test_all_scenes_and_edits_are_read_from_the_library_at_expansion_time(monkeypatch):
    """Scenes and edits added to dualnerf.scenes.library (issue 14) join the comparison automatically."""
    from dualnerf.scenes import library
    from dualnerf.scenes.library import BUILDERS, CAMPSITE, SCENES, EditDef
    from dualnerf.scenes.render import Variant

    melt = EditDef("melt", "Melt it", "a scene", "a melted scene", Variant("melt", snow=True))
    monkeypatch.setitem(library.SCENES, "camp2", CAMPSITE)
    monkeypatch.setitem(library.BUILDERS, "camp2", (BUILDERS["campsite"][0], (melt,)))
    assert "camp2" in SCENES
    wf = load_workflow(WORKFLOWS / "comparison.toml", [NO_USER])
    assert ("camp2", "melt") in {(c.scene, c.edit_id) for c in wf.cells}
    assert wf.report_dir == Path("reports/comparison")


def test_sweep_blend_is_wmax_by_lambda_with_one_in2n_reference(tmp_path):
    wf = load_workflow(WORKFLOWS / "sweep_blend.toml", [NO_USER])
    dual = [c for c in wf.cells if c.label == "DualNeRF"]
    grid = sorted((dict(c.params)["w_max"], dict(c.params)["lambda"]) for c in dual)
    assert grid == sorted((w, lam) for w in (0.03, 0.1, 0.3) for lam in (0.0025, 0.005, 0.01))
    for cell in dual:
        p = cell.edit.params
        w_max, lam = dict(cell.params)["w_max"], dict(cell.params)["lambda"]
        assert p["w_max_density"] == p["w_max_color"] == w_max and p["blend_rate"] == lam
    in2n = [c for c in wf.cells if c.label == "IN2N"]
    assert len(in2n) == 1 and dict(in2n[0].params) == {"w_max": 0.1, "lambda": 0.005}
    # the paper-value DualNeRF cell is the ablation's full model (the same key: cached once)
    ablation = load_workflow(WORKFLOWS / "ablation.toml", [NO_USER])
    full = next(c for c in ablation.cells if c.label == "DF+SA+CCI")
    paper = next(c for c in dual if dict(c.params) == {"w_max": 0.1, "lambda": 0.005})
    keyed = _keyed(wf, tmp_path)
    assert keyed[paper.evaluate].key == _keyed(ablation, tmp_path)[full.evaluate].key


def test_set_takes_lists_a_list_for_a_scalar_param_is_an_axis():
    wf = load_workflow(WORKFLOWS / "ablation.toml", [NO_USER, "seeds=[0,1,2]", "methods=[\"IN2N\",\"DF\"]",
                                                     "edit.w_max_color=[0.05,0.1,0.3]"])
    edited = [c for c in wf.cells if not c.is_original]
    assert len(edited) == 2 * 3 * 3
    assert {dict(c.params)["edit.w_max_color"] for c in edited} == {0.05, 0.1, 0.3}
    assert all(c.edit.params["w_max_color"] == dict(c.params)["edit.w_max_color"] for c in edited)
    assert wf.cells[0].params == ()          # the unedited row reads no edit axis
    # a single value fixes the parameter, replacing an [axes] entry of the file
    wf = load_workflow(WORKFLOWS / "sweep_blend.toml", [NO_USER, "lambda=[0.02]", "exclude=[]"])
    assert {dict(c.params)["lambda"] for c in wf.cells if c.label == "DualNeRF"} == {0.02}


def test_multi_scene_grid_report_dir_and_scene_edits(tmp_path):
    wf = load_workflow(WORKFLOWS / "smoke.toml", [NO_USER, "scenes=[\"tiny\",\"campsite\"]", "edits=\"all\"",
                                                  "report_dir=reports/two"])
    from dualnerf.scenes.library import BUILDERS

    # "all" is every edit the scene library lists for the scene (it grows: campsite gained "canoe").
    expected = {(scene, e.id) for scene in ("tiny", "campsite") for e in BUILDERS[scene][1]}
    assert {("tiny", "snow"), ("campsite", "autumn"), ("campsite", "canoe")} <= expected
    assert {(c.scene, c.edit_id) for c in wf.cells} == expected
    assert wf.report_dir == Path("reports/two") and wf.scenes == ["tiny", "campsite"]
    keyed = _keyed(wf, tmp_path)
    assert len([s for s in keyed if s.stage == "fit"]) == 2
    with pytest.raises(WorkflowError, match=r"uses \{scene\} but the grid has 2 scenes"):
        load_workflow(WORKFLOWS / "ablation.toml", [NO_USER, "scenes=[\"tiny\",\"campsite\"]"])
    wf = load_workflow(WORKFLOWS / "comparison.toml", [NO_USER, "exclude=[]"])
    assert wf.report_dir == Path("reports/comparison") and "tiny" in wf.scenes


def test_per_scene_edits_and_filters():
    wf = load_workflow(WORKFLOWS / "comparison.toml", [
        NO_USER, "exclude=[]", "scenes=[\"tiny\", \"campsite\"]", "edits={tiny = [\"snow\"], campsite = \"all\"}",
        "include=[{scene = \"tiny\"}, {method = \"DualNeRF\", seed = 0}]"])
    edited = [c for c in wf.cells if not c.is_original]
    assert {(c.scene, c.edit_id) for c in edited if c.scene == "tiny"} == {("tiny", "snow")}
    assert len([c for c in edited if c.scene == "tiny"]) == 9
    assert {(c.label, c.seed) for c in edited if c.scene == "campsite"} == {("DualNeRF", 0)}


@pytest.mark.parametrize("overrides, fragment", [
    (["edit.w_max_colour=[0.1,0.3]"], r"unknown parameter 'edit.w_max_colour'; known edit parameters: .*w_max_color"),
    (["fit.iteration=5"], "unknown parameter 'fit.iteration'"),
    (["edit.seed=[1,2]"], "set by the workflow from seeds"),
    (["methods=[\"DF+XX\"]"], "unknown method 'DF\\+XX'"),
    (["methods=[\"per-frame\"]", "edit.w_max_color=[0.1,0.3]"], "axis 'edit.w_max_color' .* is read by no cell"),
    (["exclude=[{method = \"IN2M\"}]"], "never takes the value 'IN2M'"),
    (["include=[{colour = 1}]"], "unknown axis 'colour'"),
    (["edit.w_max_color=[]"], "non-empty list"),
    (["w_max=[0.1]"], "unknown key 'w_max'"),
])
def test_typos_and_unread_axes_are_refused_before_anything_runs(overrides, fragment):
    with pytest.raises(WorkflowError, match=fragment):
        load_workflow(WORKFLOWS / "ablation.toml", [NO_USER, *overrides])


def test_grouped_axis_member_cannot_be_set_alone():
    with pytest.raises(WorkflowError, match="grouped axis 'w_max'"):
        load_workflow(WORKFLOWS / "sweep_blend.toml", [NO_USER, "edit.w_max_color=0.2"])


def test_per_frame_rows_do_not_multiply_over_edit_only_axes():
    wf = load_workflow(WORKFLOWS / "sweep_blend.toml", [NO_USER, "methods=[\"per-frame\",\"DualNeRF\"]",
                                                        "exclude=[]"])
    per_frame = [c for c in wf.cells if c.label == "per-frame"]
    assert len(per_frame) == 1 and per_frame[0].params == ()
    # the editor choice does reach the per-frame baseline (same editor as the IDU rows)
    wf = load_workflow(WORKFLOWS / "comparison.toml", [NO_USER, "edit.editor=[\"synthetic\",\"ip2p\"]",
                                                       "methods=[\"per-frame\"]", "seeds=[0]"])
    assert {c.perframe.params["editor"] for c in wf.cells if c.perframe is not None} == {"synthetic", "ip2p"}
    # only the emulator needs the ground truth re-rendered; it is one step per scene edit
    assert {c.perframe.params["editor"]: "gtviews" in c.perframe.inputs for c in wf.cells if c.perframe} == \
        {"synthetic": True, "ip2p": False}
    assert len([s for s in wf.steps if s.stage == "gtviews"]) == len({(c.scene, c.edit_id) for c in wf.cells})


def test_hundred_cell_grid_expands_with_shared_upstream():
    wf = load_workflow(WORKFLOWS / "sweep_blend.toml", [NO_USER, "seeds=[0,1,2,3]", "exclude=[]",
                                                        "methods=[\"DualNeRF\",\"DF+SA\",\"IN2N\"]"])
    assert len(wf.cells) == 1 + 3 * 4 * 9
    assert len([s for s in wf.steps if s.stage == "fit"]) == 1


# --- reruns compute only new cells (the engine on cheap stand-ins with the real Params) ----------------

RUNS_LOG = "DUALNERF_TEST_GRID_LOG"


class _Fake:
    """Writes one file; appends its stage and params to the log so the test counts computations."""

    version = "1"

    def run(self, ctx) -> None:
        import dataclasses
        import os

        (ctx.out_dir / "out.json").write_text(json.dumps(dataclasses.asdict(ctx.params)))
        with open(os.environ[RUNS_LOG], "a") as log:
            log.write(json.dumps({"stage": self.name, **dataclasses.asdict(ctx.params)}, default=str) + "\n")


def _fake(stage_name: str, real: str):
    from pipeline.registry import load_ref
    from pipeline.stage import Stage

    real_cls = load_ref(real)
    return type(f"Fake_{stage_name}", (_Fake, Stage), {
        "name": stage_name, "Params": real_cls.Params, "upstream": real_cls.upstream,
        "external": real_cls.external, "nonsemantic_params": real_cls.nonsemantic_params})


_REAL = {"scene": "stages.scene:SceneStage", "preprocess": "stages.preprocess:PreprocessStage",
         "fit": "stages.fit:FitStage", "edit": "stages.edit:EditStage",
         "perframe": "stages.perframe:PerFrameStage", "evaluate": "stages.evaluate:EvaluateStage",
         "gtviews": "stages.gtviews:GroundTruthViewsStage"}
FakeScene, FakePreprocess, FakeFit, FakeEdit, FakePerframe, FakeEvaluate, FakeGtviews = (
    _fake(n, ref) for n, ref in _REAL.items())
FAKES = {name: f"tests.test_workflow_grid:Fake{name.capitalize()}" for name in _REAL}


def test_rerun_and_added_seed_or_value_compute_only_new_cells(tmp_path, monkeypatch):
    from pipeline.executors import SerialExecutor
    from pipeline.runner import run_steps
    from pipeline.store import Store

    monkeypatch.setattr("stages.STAGES", FAKES)
    log = tmp_path / "computed.jsonl"
    monkeypatch.setenv(RUNS_LOG, str(log))
    store = Store(tmp_path / "cache")

    def run(*overrides):
        log.write_text("")
        wf = load_workflow(WORKFLOWS / "sweep_blend.toml", [NO_USER, "methods=[\"per-frame\",\"DualNeRF\"]",
                                                            "exclude=[]", *overrides])
        result = run_steps(wf.steps, registry=FAKES, store=store, executor=SerialExecutor(1),
                           run_dir=tmp_path / "runs" / "r", quiet=True)
        assert not result.failed
        return [json.loads(line) for line in log.read_text().splitlines()]

    first = run("w_max=[0.1]", "lambda=[0.005]")
    assert sorted(e["stage"] for e in first) == ["edit", "evaluate", "evaluate", "evaluate", "fit", "gtviews",
                                                 "perframe", "preprocess", "scene"]
    assert run("w_max=[0.1]", "lambda=[0.005]") == [], "a rerun of a finished grid computes nothing"
    added_seed = run("w_max=[0.1]", "lambda=[0.005]", "seeds=[0,1]")
    assert sorted((e["stage"], e.get("seed")) for e in added_seed if e["stage"] != "evaluate") == [
        ("edit", 1), ("perframe", 1)]           # the ground-truth views are shared by the seeds
    assert len([e for e in added_seed if e["stage"] == "evaluate"]) == 2
    added_value = run("w_max=[0.1,0.3]", "lambda=[0.005]", "seeds=[0,1]")
    assert sorted((e["stage"], e.get("w_max_color")) for e in added_value) == [
        ("edit", 0.3), ("edit", 0.3), ("evaluate", None), ("evaluate", None)]


def test_dry_run_prints_the_grid_size_and_every_cell(tmp_path, capsys):
    from experiments.cli import main

    code = main(["--cache", str(tmp_path / "cache"), "run", str(WORKFLOWS / "sweep_blend.toml"), "--dry-run",
                 "--set", NO_USER, "--set", "seeds=[0,1]"])
    out = capsys.readouterr().out
    assert code == 0
    assert "grid: 21 cells (1 scene x 1 edit x 2 method x 2 seed x 3 w_max x 3 lambda" in out
    assert "[20] scene=campsite edit=snow method=DualNeRF seed=1 w_max=0.3 lambda=0.01" in out
    assert out.count("pending") == 3 + 1 + 2 * 20          # scene, preprocess, fit, original; edit+evaluate per cell
    assert not (tmp_path / "cache" / "objects").exists() or not any((tmp_path / "cache" / "objects").iterdir())


def test_failure_mode_controls_cross_the_rows_with_lock_in_and_share_the_ablation_cells(tmp_path):
    """workflows/ablation_failure_modes.toml (issue 29): campsite/snow x 6 rows x lock_in {on, off} x 3
    seeds (36 edits) + campsite/blue_tent x {IN2N, DF, DualNeRF} x lock_in on x 3 seeds (9); its snow
    lock_in=True cells are `make ablation`'s cells (same keys)."""
    wf = load_workflow(WORKFLOWS / "ablation_failure_modes.toml", [NO_USER])
    edited = [c for c in wf.cells if c.edit is not None]
    assert len(edited) == 45
    snow = [c for c in edited if c.edit_id == "snow"]
    assert len(snow) == 36 and {dict(c.params)["lock_in"] for c in snow} == {True, False}
    assert all(c.edit.params["emulator_lock_in"] is dict(c.params)["lock_in"] for c in edited)
    tent = [c for c in edited if c.edit_id == "blue_tent"]
    assert sorted({c.label for c in tent}) == ["DF", "DF+SA+CCI", "baseline"] and len(tent) == 9
    assert all(dict(c.params)["lock_in"] is True for c in tent)
    ablation = load_workflow(WORKFLOWS / "ablation.toml", [NO_USER])
    keys_f = _keyed(wf, tmp_path)
    keys_a = _keyed(ablation, tmp_path)
    on = {keys_f[c.edit].key for c in snow if dict(c.params)["lock_in"]}
    assert {keys_a[c.edit].key for c in ablation.cells if c.edit is not None} == on
