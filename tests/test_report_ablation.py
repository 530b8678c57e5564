"""The report's ablation sections against hand-built inputs: CCI's precision and recall at flagging the
emulator's failed calls (a known confusion matrix in updates.jsonl), the in-mask vs outside-mask scatter
(one point per row and seed), the metrics that see the ground truth, and the failure-mode axis's label."""
import json
import math

import cv2
import pytest

from experiments import report as R
from experiments.methods import Method
from experiments.report import flagging as FL
from experiments.report import joint as J
from tests.test_report import make_evaluate


def _updates(folder, calls):
    """updates.jsonl from (failed, flagged) pairs: flagged calls get score_ratio < 1."""
    folder.mkdir(parents=True)
    with open(folder / "updates.jsonl", "w") as handle:
        for i, (failed, flagged) in enumerate(calls):
            ratio = 0.8 if flagged else 1.1
            handle.write(json.dumps({"iteration": 10 * i, "view": i, "score": ratio / 2, "score_ratio": ratio,
                                     "editor": {"kind": "synthetic", "failed": failed}}) + "\n")
    return folder


# Seed 0: 10 calls, 3 failed; 4 flagged, 2 of them failed (TP 2, FP 2, FN 1, TN 5).
SEED0 = [(True, True), (True, True), (True, False), (False, True), (False, True)] + [(False, False)] * 5
# Seed 1: 10 calls, 2 failed, both flagged and nothing else (TP 2, FP 0, FN 0, TN 8).
SEED1 = [(True, True), (True, True)] + [(False, False)] * 8


def _rows(tmp_path, sees=("gt_psnr_edit", "gt_psnr_inside", "gt_psnr_background")):
    rows = []
    original = make_evaluate(tmp_path / "orig", {"gt_psnr_edit": 12.0, "gt_psnr_inside": 9.0,
                                                  "gt_psnr_background": math.inf}, (90, 140, 60), editor=None)
    rows.append(R.ReportRow(Method.original("original"), None, original, scene="tiny", edit="snow"))
    cells = {("baseline", False): [(14.0, 25.0, SEED0), (15.0, 26.0, SEED1)],
             ("CCI", True): [(16.0, 24.0, SEED0), (17.0, 23.0, SEED1)]}
    for (label, cci), seeds in cells.items():
        for seed, (inside, outside, calls) in enumerate(seeds):
            ev = make_evaluate(tmp_path / f"e_{label}_{seed}", {"gt_psnr_edit": 18.0 + seed, "gt_psnr_inside": inside,
                                                               "gt_psnr_background": outside}, (230, 230, 240))
            ed = _updates(tmp_path / f"x_{label}_{seed}", calls)
            rows.append(R.ReportRow(Method.idu(False, False, cci, label=label), seed, ev, ed, scene="tiny",
                                    edit="snow"))
    for row in rows:
        doc = json.loads((row.evaluate_dir / "metrics.json").read_text())
        doc["sees_ground_truth"] = [m for m in sees if m in doc["metrics"]]
        (row.evaluate_dir / "metrics.json").write_text(json.dumps(doc))
    return rows


def test_flagging_precision_and_recall_from_a_known_confusion_matrix(tmp_path):
    out = tmp_path / "report"
    R.build_report(_rows(tmp_path), out, title_info={})
    entries = {e["label"]: e for e in json.loads((out / "report.json").read_text())["cci_flagging"]}
    cci = entries["CCI"]
    # Pooled: TP 4, flagged 6, failed 5, calls 20.
    assert (cci["calls"], cci["failed"], cci["flagged"], cci["flagged_failed"]) == (20, 5, 6, 4)
    assert cci["precision"] == pytest.approx(4 / 6) and cci["recall"] == pytest.approx(4 / 5)
    assert cci["base_rate"] == pytest.approx(0.25) and cci["cci"] is True
    assert [u["precision"] for u in cci["units"]] == [pytest.approx(0.5), 1.0]
    assert [u["recall"] for u in cci["units"]] == [pytest.approx(2 / 3), 1.0]
    assert entries["baseline"]["cci"] is False and "original" not in entries
    markdown = (out / "table.md").read_text()
    assert "## CCI: flagging the emulator's failed calls" in markdown
    assert "| CCI | ✓ | 2 | 20 | 5 | 0.25 | 6 | 0.67 | 0.50, 1.00 | 0.80 | 0.67, 1.00 |" in markdown
    assert "| baseline | ✗ (logged only) | 2 | 20 |" in markdown
    page = (out / "index.html").read_text()
    assert "CCI: flagging the emulator" in page and "0.50, 1.00" in page


def test_flagging_skips_rows_without_records_or_failure_flags(tmp_path):
    rows = _rows(tmp_path)
    (rows[1].edit_dir / "updates.jsonl").unlink()               # baseline seed 0: no records
    ip2p = tmp_path / "x_ip2p"
    ip2p.mkdir()
    (ip2p / "updates.jsonl").write_text(json.dumps({"score": 0.4, "score_ratio": 0.9, "editor": {"kind": "ip2p"}}))
    rows[2] = R.ReportRow(rows[2].method, 1, rows[2].evaluate_dir, ip2p, scene="tiny", edit="snow")
    _, table = R.aggregate(rows, [R.load_metrics(r.evaluate_dir) for r in rows])
    assert [e["label"] for e in FL.flagging_rows(rows, table)] == ["CCI"]


def test_joint_scatter_has_one_point_per_row_and_seed(tmp_path):
    rows = _rows(tmp_path)
    docs = [R.load_metrics(r.evaluate_dir) for r in rows]
    points = J.scatter_points(rows, docs)
    assert points == {("tiny", "snow"): {("baseline", ()): [(0, 14.0, 25.0), (1, 15.0, 26.0)],
                                         ("CCI", ()): [(0, 16.0, 24.0), (1, 17.0, 23.0)]}}
    out = tmp_path / "report"
    page = R.build_report(rows, out, title_info={}).read_text()
    image = cv2.imread(str(out / J.SCATTER))
    assert image is not None and image.shape[0] > 200 and image.shape[1] > 200
    assert json.loads((out / "report.json").read_text())["joint_scatter"] == J.SCATTER
    assert f"<img src='{J.SCATTER}'" in page and "edits less" in page


def test_report_names_the_metrics_that_see_the_ground_truth(tmp_path):
    rows = _rows(tmp_path, sees=("gt_psnr_edit", "gt_psnr_inside"))
    out = tmp_path / "report"
    page = R.build_report(rows, out, title_info={}).read_text()
    entries = json.loads((out / "report.json").read_text())["sees_ground_truth"]
    assert [(e["metric"], e["rows"]) for e in entries] == [("gt_psnr_edit", "all"), ("gt_psnr_inside", "all")]
    markdown = (out / "table.md").read_text()
    assert "- PSNR_gt (gt_psnr_edit): every row" in markdown and "gt_psnr_background" not in \
        markdown.split("## Metrics that see the ground truth")[1]
    assert "Metrics that see the ground truth" in page and "emulator" in page


def test_lock_in_axis_labels_the_rows(tmp_path):
    rows = []
    for lock in (True, False):
        for seed in (0, 1):
            ev = make_evaluate(tmp_path / f"e_{lock}_{seed}", {"gt_psnr_edit": 18.0 + seed + lock,
                                                              "gt_psnr_inside": 15.0, "gt_psnr_background": 25.0},
                               (230, 230, 240))
            rows.append(R.ReportRow(Method.idu(False, False, False, label="baseline"), seed, ev, scene="tiny",
                                    edit="snow", params=(("lock_in", lock),)))
    out = tmp_path / "report"
    R.build_report(rows, out, title_info={})
    markdown = (out / "table.md").read_text()
    assert "| baseline [lock_in=True] |" in markdown and "| baseline [lock_in=False] |" in markdown
