"""The report's statistics from fake evaluate folders: mean ± std with n, the paired difference to the
reference row with its bootstrap interval (closed forms: identical rows, constant shifts), per-scene tables
beside the aggregate, and parameter-axis plots."""
import csv
import json
import math

import numpy as np
import pytest

from experiments import report as R
from experiments.methods import Method
from tests.test_report import make_evaluate
from tests.test_report_command import setup  # noqa: F401  (fixture)

METRIC = "clip_text_image_direction"
SCENES = ("tiny", "room")


def _grid(tmp_path, *, shift=0.05, seeds=(0, 1, 2), noise=(0.0, 0.02, -0.01)):
    """baseline over 2 scenes x 3 seeds; 'same' = baseline exactly; 'shifted' = baseline + shift per unit;
    'sweep' at w in {0.1, 0.3} = baseline + w; 'room only' runs one scene."""
    rows = []
    for scene_i, scene in enumerate(SCENES):
        for seed in seeds:
            base = 0.1 + 0.1 * scene_i + noise[seed]
            cells = {"baseline": ((), base), "same": ((), base), "shifted": ((), base + shift)}
            cells.update({f"sweep{w}": ((("edit.w_max_color", w),), base + w) for w in (0.1, 0.3)})
            if scene == "room":
                cells["room only"] = ((), base + 1.0)
            for name, (params, value) in cells.items():
                label = "sweep" if name.startswith("sweep") else name
                folder = make_evaluate(tmp_path / f"{name}_{scene}_{seed}",
                                       {METRIC: value, "gt_psnr_edit": 20.0 + value}, (200, 200, 200))
                rows.append(R.ReportRow(Method.idu(label != "baseline", False, False, label=label), seed, folder,
                                        scene=scene, edit="snow", params=params))
    return rows


def _by_label(doc):
    return {(r["label"], tuple(tuple(p) for p in r["params"])): r for r in doc["rows"]}


def test_report_shows_mean_std_n_and_paired_intervals(tmp_path):
    out = tmp_path / "report"
    R.build_report(_grid(tmp_path), out, title_info={})
    doc = json.loads((out / "table.json").read_text())
    rows = _by_label(doc)
    base = rows[("baseline", ())]["metrics"][METRIC]
    # Per seed, the mean over the two scenes is 0.15 + noise: mean 0.15 + mean(noise), std of the noise.
    noise = np.array([0.0, 0.02, -0.01])
    assert base["mean"] == pytest.approx(0.15 + noise.mean())
    assert base["std"] == pytest.approx(noise.std(ddof=1))
    assert base["n"] == 6 and rows[("baseline", ())]["runs"] == 6
    assert "paired" not in base                                     # the reference itself
    same = rows[("same", ())]["metrics"][METRIC]["paired"]
    assert (same["mean"], same["ci_low"], same["ci_high"], same["n_pairs"]) == (0.0, 0.0, 0.0, 6)
    assert same["ci_contains_zero"] is True and same["ci_excludes_zero"] is False
    assert (same["t_ci_low"], same["t_ci_high"]) == (0.0, 0.0)
    shifted = rows[("shifted", ())]["metrics"][METRIC]["paired"]
    assert shifted["ci_low"] == pytest.approx(0.05, abs=1e-12) and shifted["ci_high"] == pytest.approx(0.05, abs=1e-12)
    assert shifted["ci_contains_zero"] is False and shifted["ci_excludes_zero"] is True
    # Pairing uses matching units only: 'room only' has 3 units, the baseline's 3 tiny units are unpaired.
    room = rows[("room only", ())]["metrics"][METRIC]["paired"]
    assert room["n_pairs"] == 3 and room["mean"] == pytest.approx(1.0)
    assert room["unpaired"] == [] and sorted(u[0] for u in room["unpaired_reference"]) == ["tiny"] * 3
    # Rows with equal (label, params) are one row; each parameter value is its own.
    sweep = rows[("sweep", (("edit.w_max_color", 0.3),))]["metrics"][METRIC]["paired"]
    assert sweep["mean"] == pytest.approx(0.3) and sweep["ci_low"] == pytest.approx(0.3)
    assert doc["paired"]["reference"] == "baseline" and doc["paired"]["resamples"] == 10_000
    assert doc["paired"]["method"].startswith("percentile") and doc["paired"]["seed"] == 0

    markdown = (out / "table.md").read_text()
    assert "| baseline | ✗ | ✗ | ✗ | 0, 1, 2 | 6 | " in markdown
    assert f"{0.15 + noise.mean():.4f} ± {noise.std(ddof=1):.4f}" in markdown
    assert "## Difference to `baseline`" in markdown
    assert "| same | 6 | +0.0000 [+0.0000, +0.0000] incl. 0 |" in markdown
    assert "| shifted | 6 | +0.0500 [+0.0500, +0.0500] excl. 0 |" in markdown
    assert "room only: 0 unit(s) without a reference run, 3 reference unit(s) it did not run" in markdown
    assert "| sweep [edit.w_max_color=0.1] |" in markdown
    with open(out / "table.csv") as handle:
        records = {(r["variant"], r["params"]): r for r in csv.DictReader(handle)}
    assert float(records[("shifted", "")][f"{METRIC}_ci_low"]) == pytest.approx(0.05)
    assert records[("same", "")][f"{METRIC}_ci_contains_zero"] == "1"
    assert records[("same", "")][f"{METRIC}_ci_excludes_zero"] == "0"
    assert records[("shifted", "")][f"{METRIC}_ci_excludes_zero"] == "1"
    assert records[("baseline", "")][f"{METRIC}_diff"] == "" and records[("baseline", "")][f"{METRIC}_n"] == "6"

    page = (out / "index.html").read_text()
    assert "Difference to baseline" in page and "class='ns'" in page and "percentile bootstrap" in page
    assert "t interval" in page and "excl. 0" in page and "incl. 0" in page


def test_per_scene_tables_beside_the_aggregate(tmp_path):
    out = tmp_path / "report"
    R.build_report(_grid(tmp_path), out, title_info={})
    report = json.loads((out / "report.json").read_text())
    assert [(s["scene"], s["edit"]) for s in report["per_scene"]] == [("tiny", "snow"), ("room", "snow")]
    tiny = _by_label(json.loads((out / "scenes" / "tiny_snow" / "table.json").read_text()))
    # One scene: the plain mean ± std over its three seeds.
    assert tiny[("baseline", ())]["metrics"][METRIC]["mean"] == pytest.approx(0.1 + np.mean([0.0, 0.02, -0.01]))
    assert tiny[("baseline", ())]["runs"] == 3
    assert ("room only", ()) not in tiny
    assert tiny[("shifted", ())]["metrics"][METRIC]["paired"]["n_pairs"] == 3
    page = (out / "index.html").read_text()
    assert "Per scene and edit" in page and "<h3>tiny / snow</h3>" in page
    assert "scenes/tiny_snow/table.md" in page and (out / "scenes" / "room_snow" / "table.csv").is_file()
    # Images show one scene (the first), each parameter setting as its own row; 'room only' is not there.
    assert report["path_strip_rows"] == ["Original", "baseline", "same", "shifted", "sweep [edit.w_max_color=0.1]",
                                         "sweep [edit.w_max_color=0.3]"]
    assert len(report["videos"]) == len(set(report["videos"])) == 2 * 3 * 5 + 3    # distinct names per unit


def test_parameter_axis_plot(tmp_path):
    out = tmp_path / "report"
    R.build_report(_grid(tmp_path), out, title_info={})
    report = json.loads((out / "report.json").read_text())
    assert report["parameter_plots"] == ["params/edit.w_max_color.png"]
    assert (out / "params" / "edit.w_max_color.png").stat().st_size > 1000
    assert "params/edit.w_max_color.png" in (out / "index.html").read_text()


def test_single_scene_report_has_no_per_scene_section(tmp_path):
    rows = [r for r in _grid(tmp_path) if r.scene == "tiny" and not r.params]
    out = tmp_path / "report"
    R.build_report(rows, out, title_info={})
    assert not (out / "scenes").exists() and not (out / "params").exists()
    assert "Per scene and edit" not in (out / "index.html").read_text()


def test_reference_is_configurable_and_checked(tmp_path):
    rows = _grid(tmp_path)
    out = tmp_path / "report"
    R.build_report(rows, out, title_info={}, reference="shifted")
    doc = _by_label(json.loads((out / "table.json").read_text()))
    assert doc[("baseline", ())]["metrics"][METRIC]["paired"]["mean"] == pytest.approx(-0.05)
    assert "paired" not in doc[("shifted", ())]["metrics"][METRIC]
    with pytest.raises(R.ReportError, match="reference row 'IN2N' is not among the report's rows"):
        R.build_report(rows, tmp_path / "r2", title_info={}, reference="IN2N")
    # Without a baseline row and no reference asked for: no difference section, no error.
    R.build_report([r for r in rows if r.label != "baseline"], tmp_path / "r3", title_info={})
    assert "Difference to" not in (tmp_path / "r3" / "table.md").read_text()


def test_a_repeated_unit_is_a_clear_error(tmp_path):
    rows = _grid(tmp_path, seeds=(0,), noise=(0.0,))
    duplicate = next(r for r in rows if r.label == "same")
    with pytest.raises(R.ReportError, match="two results for row same at scene 'tiny'"):
        R.build_report(rows + [duplicate], tmp_path / "r", title_info={})


def test_infinite_values_have_no_interval_and_the_unedited_scene_is_not_compared(tmp_path):
    # A row whose background is identical to the original has PSNR +inf: its difference cannot be stated.
    # The unedited scene's row is shown in the table but is not a method: it gets no difference.
    original = R.ReportRow(Method.original("original"), None,
                           make_evaluate(tmp_path / "o", {"gt_psnr_background": math.inf}, (1, 2, 3)))
    rows = [original]
    for seed in range(3):
        rows.append(R.ReportRow(Method.idu(False, False, False, label="baseline"), seed,
                                make_evaluate(tmp_path / f"b{seed}", {"gt_psnr_background": 20.0 + seed}, (1, 2, 3))))
        rows.append(R.ReportRow(Method.idu(True, False, False, label="DF"), seed,
                                make_evaluate(tmp_path / f"d{seed}", {"gt_psnr_background": math.inf}, (1, 2, 3))))
    R.build_report(rows, tmp_path / "r", title_info={})
    doc = _by_label(json.loads((tmp_path / "r" / "table.json").read_text()))
    paired = doc[("DF", ())]["metrics"]["gt_psnr_background"]["paired"]
    assert paired["n_pairs"] == 0 and paired["mean"] is None and len(paired["non_finite"]) == 3
    assert "paired" not in doc[("original", ())]["metrics"]["gt_psnr_background"]
    table_md = (tmp_path / "r" / "table.md").read_text()
    assert "| DF | 0 | n/a |" in table_md
    differences = table_md.split("## Difference to")[1]
    assert "Original Scene" not in differences and "| Original Scene |" in table_md


def test_component_effects_pair_each_component_with_its_partner_per_failure_mode(tmp_path):
    # PSNR_gt per (lock_in, seed): baseline b; DF = b + 1 everywhere; DF+SA = DF + 0.5 with lock-in on and
    # DF + (seed noise around 0) with it off; CCI = b + 0.2 with lock-in on only (no partner row DF+CCI).
    noise = (0.3, -0.1, -0.2)
    rows = []
    for lock_in in (True, False):
        for seed in range(3):
            base = 15.0 + seed * 0.7 + (0.4 if lock_in else 0.0)
            values = {"baseline": base, "DF": base + 1.0,
                      "DF+SA": base + 1.0 + (0.5 if lock_in else noise[seed])}
            if lock_in:
                values["CCI"] = base + 0.2
            for label, value in values.items():
                folder = make_evaluate(tmp_path / f"{label}_{lock_in}_{seed}", {"gt_psnr_edit": value}, (200,) * 3)
                rows.append(R.ReportRow(Method.parse(label), seed, folder, scene="campsite", edit="snow",
                                        params=(("lock_in", lock_in),)))
    R.build_report(rows, tmp_path / "r", title_info={})
    effects = json.loads((tmp_path / "r" / "report.json").read_text())["component_effects"]
    found = {(e["component"], e["row"], e["partner"], e["params"][0][1]): e["differences"]["gt_psnr_edit"]
             for e in effects}
    assert set(found) == {("DF", "DF", "baseline", True), ("DF", "DF", "baseline", False),
                          ("SA", "DF+SA", "DF", True), ("SA", "DF+SA", "DF", False),
                          ("CCI", "CCI", "baseline", True)}           # DF+SA has no SA-free partner with CCI
    assert found[("DF", "DF", "baseline", True)]["mean"] == pytest.approx(1.0)
    sa_on, sa_off = found[("SA", "DF+SA", "DF", True)], found[("SA", "DF+SA", "DF", False)]
    assert sa_on["mean"] == pytest.approx(0.5) and sa_on["ci_excludes_zero"] is True and sa_on["n_pairs"] == 3
    assert sa_off["mean"] == pytest.approx(np.mean(noise)) and sa_off["ci_excludes_zero"] is False
    table_md = (tmp_path / "r" / "table.md").read_text()
    assert "## Component effects by failure-mode setting" in table_md
    assert "| SA | DF+SA − DF | lock_in=True | 3 | +0.50 [+0.50, +0.50] excl. 0 |" in table_md
    assert "Component effects by failure-mode setting" in (tmp_path / "r" / "index.html").read_text()


def test_report_workflow_passes_the_reference_on(setup, tmp_path):  # noqa: F811 (the fixture)
    from experiments.commands.report import report_workflow
    from tests.test_report_command import _publish

    workflow, store, keys, values = setup
    for cell in workflow.cells[1:]:
        _publish(store, keys[cell.evaluate].key,
                 lambda f, v=values[cell.label]: make_evaluate(f, {METRIC: v}, (200, 200, 200)))
    report_workflow(workflow, store, tmp_path / "r", reference="DF+SA+CCI")
    doc = json.loads((tmp_path / "r" / "table.json").read_text())
    assert doc["paired"]["reference"] == "DF+SA+CCI"
    baseline = _by_label(doc)[("baseline", ())]["metrics"][METRIC]["paired"]
    assert baseline["mean"] == pytest.approx(-0.1) and baseline["n_pairs"] == 1 and baseline["ci_low"] is None
