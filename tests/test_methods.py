"""One model of a method (experiments.methods): names, flags, kinds, the edit step's parameters, the
older `variants` rows, and what the report prints for each kind."""
import json

import pytest

from experiments.methods import ORIGINAL, Method, MethodError, names_from_variants


def test_names_parse_to_flags_and_kinds():
    assert Method.parse("IN2N").flags == (False, False, False) and Method.parse("IN2N").label == "IN2N"
    assert Method.parse("DualNeRF").flags == (True, True, True)
    assert Method.parse("SA+DF") == Method.idu(True, True, False)            # any order, canonical label
    assert Method.parse("SA+DF").label == "DF+SA"
    assert Method.parse("baseline") == Method("baseline", "idu")
    per_frame = Method.parse("per-frame")
    assert per_frame.is_per_frame and per_frame.flags is None and not per_frame.is_original
    assert ORIGINAL.is_original and ORIGINAL.label == "Original scene" and ORIGINAL.flags is None
    with pytest.raises(MethodError, match="unknown method 'DF\\+DF'"):
        Method.parse("DF+DF")
    with pytest.raises(ValueError, match="cannot switch on"):
        Method("x", "per-frame", dual_field=True)


def test_edit_params_are_the_edit_stage_flags():
    from dataclasses import fields

    from stages.edit import EditParams

    params = Method.parse("DF+CCI").edit_params()
    assert params == {"dual_field": True, "annealing": False, "consistency": True}
    assert set(params) <= {f.name for f in fields(EditParams)}
    with pytest.raises(ValueError, match="runs no edit stage"):
        Method.per_frame().edit_params()


def test_variants_rows_become_the_labels_they_always_had():
    rows = [[False, False, False], [True, False, False], [True, True, True], [False, True, True]]
    assert names_from_variants(rows) == ["baseline", "DF", "DF+SA+CCI", "SA+CCI"]
    assert [Method.parse(n).flags for n in names_from_variants(rows)] == [tuple(r) for r in rows]
    with pytest.raises(MethodError, match="three booleans"):
        names_from_variants([[True, False]])


def test_report_marks_per_kind():
    assert Method.parse("DF+SA").marks() == ("✓", "✓", "✗")
    assert Method.parse("per-frame").marks() == ("–", "–", "–")         # not applicable, not "✗ ✗ ✗"
    assert ORIGINAL.marks() == ("", "", "")


def test_a_per_frame_row_is_not_printed_as_the_single_field_baseline(tmp_path):
    from experiments import report as R
    from tests.test_report import make_evaluate

    values = {"clip_text_image_direction": 0.1}
    rows = [R.ReportRow(Method.original("original"), None, make_evaluate(tmp_path / "o", values, (1, 2, 3))),
            R.ReportRow(Method.parse("per-frame"), 0, make_evaluate(tmp_path / "p", values, (4, 5, 6))),
            R.ReportRow(Method.parse("IN2N"), 0, make_evaluate(tmp_path / "i", values, (7, 8, 9)))]
    R.build_report(rows, tmp_path / "r", title_info={})
    table = (tmp_path / "r" / "table.md").read_text()
    assert "| per-frame | – | – | – |" in table and "| IN2N | ✗ | ✗ | ✗ |" in table
    doc = json.loads((tmp_path / "r" / "table.json").read_text())
    kinds = {r["label"]: (r["kind"], r["dual_field"]) for r in doc["rows"]}
    assert kinds == {"original": ("original", None), "per-frame": ("per-frame", None), "IN2N": ("idu", False)}
    html = (tmp_path / "r" / "index.html").read_text()
    assert html.count("<td style='text-align:center'>–</td>") == 3


def test_presets_use_methods_and_the_older_syntax_keeps_its_labels_and_keys(tmp_path):
    """The shipped workflows write `methods`; a file in the older `variants` syntax expands to the same
    steps (tests/test_workflow_keys_recorded.py pins the keys of the shipped ones)."""
    import tomllib

    from experiments.workflow import load_workflow
    from tests.workflow_key_record import ROOT, describe

    for path in sorted((ROOT / "workflows").glob("*.toml")):
        assert "variants" not in tomllib.loads(path.read_text())["workflow"], path.name
    ablation = ROOT / "workflows" / "ablation.toml"
    older = tmp_path / "ablation.toml"
    older.write_text(ablation.read_text().replace(
        'methods = ["baseline", "DF", "DF+SA", "CCI", "DF+CCI", "DF+SA+CCI"]',
        "variants = [[false, false, false], [true, false, false], [true, true, false], [false, false, true], "
        "[true, false, true], [true, true, true]]"))
    assert older.read_text() != ablation.read_text()
    new = load_workflow(ablation, ["scenes_dir=/nonexistent"])
    old = load_workflow(older, ["scenes_dir=/nonexistent"])
    assert describe(old) == describe(new)
    assert [c.label for c in old.cells if c.seed in (None, 0)] == [
        "Original scene", "baseline", "DF", "DF+SA", "CCI", "DF+CCI", "DF+SA+CCI"]


def test_no_methods_is_the_reconstruction_alone_and_shares_the_ablations_steps():
    from experiments.workflow import WorkflowError, load_workflow
    from tests.workflow_key_record import ROOT, describe

    wf = load_workflow(ROOT / "workflows" / "reconstruct.toml", ["scenes_dir=/nonexistent"])
    assert [c.label for c in wf.cells] == ["Original scene"] and wf.cells[0].is_original
    assert [s.stage for s in wf.steps] == ["scene", "preprocess", "fit", "evaluate"]
    ablation = load_workflow(ROOT / "workflows" / "ablation.toml", ["scenes_dir=/nonexistent"])
    assert describe(wf)["cells"][0] == describe(ablation)["cells"][0]       # the same unedited row and keys
    with pytest.raises(WorkflowError, match="empty only with the unedited rows"):
        load_workflow(ROOT / "workflows" / "reconstruct.toml", ["scenes_dir=/nonexistent", "original=false"])
    with pytest.raises(WorkflowError, match="is read by no cell"):
        load_workflow(ROOT / "workflows" / "reconstruct.toml", ["scenes_dir=/nonexistent", "edit.lr=[0.1,0.2]"])
