"""The report from a small constructed grid: every row and file present, statistics and best marks right,
and index.html referencing only files that exist."""
import csv
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from dualnerf import metrics as M
from dualnerf.video import write_mp4
from experiments import report as R
from experiments.methods import Method

VIEWS = ["view_001.png", "view_005.png", "view_009.png"]


def _png(path: Path, colour) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    image = np.zeros((24, 32, 3), np.uint8)
    image[:] = colour
    image[6:18, 8:24] = (255 - np.array(colour)) // 2
    assert cv2.imwrite(str(path), image[..., ::-1])


def make_evaluate(folder: Path, values: dict, colour, *, encoder="proxy", editor="synthetic", gt=True,
                  lpips="lpips-v0.1:alex"):
    """A finished evaluate result folder as stages/evaluate.py writes it (metrics.json, views/, path.mp4)."""
    folder.mkdir(parents=True)
    doc = {"format": M.METRICS_FORMAT, "version": M.METRICS_VERSION,
           "encoder": {"kind": encoder}, "editor": None if editor is None else {"kind": editor},
           "views": {"names": VIEWS, "split": "heldout"},
           "metrics": {name: {"value": M.json_value(v), "symbol": M.METRICS[name].symbol,
                              "higher_is_better": M.METRICS[name].higher_is_better,
                              **({"encoder": encoder} if M.METRICS[name].uses_encoder else {}),
                              **({"lpips": lpips} if M.METRICS[name].uses_lpips else {})}
                       for name, v in values.items()},
           "lpips": {"tag": lpips}}
    (folder / "metrics.json").write_text(json.dumps(doc))
    for name in VIEWS:
        _png(folder / "views" / "original" / name, (90, 140, 60))
        _png(folder / "views" / "edited" / name, colour)
        if gt:
            _png(folder / "views" / "gt_edit" / name, (240, 240, 250))
    for n in range(8):
        _png(folder / "frames" / "original" / f"{n:04d}.png", (90, 140, 60 + 20 * n))
        _png(folder / "frames" / "edited" / f"{n:04d}.png", colour)
    write_mp4([np.full((16, 16, 3), colour, np.uint8)] * 3, folder / "path.mp4", fps=4)
    return folder


def make_edit(folder: Path, scale: float):
    """An edit result's curves.json in the edit stage's column layout."""
    folder.mkdir(parents=True)
    steps = list(range(0, 100, 10))
    curves = {"iteration": steps, "loss": [scale / (1 + s) for s in steps], "psnr": [20.0 + s / 10 for s in steps],
              "blend_density": [0.1 * np.tanh(0.005 * s) for s in steps],
              "blend_color": [0.1 * np.tanh(0.005 * s) for s in steps],
              "temperature": [1 / np.log10(10 + s) for s in steps],
              "cci_weight_min": [None] * len(steps), "cci_weight_max": [None] * len(steps),
              "updates": {"iteration": [0, 0, 10, 20, 30], "accepted": [None, True, False, True, True]}}
    (folder / "curves.json").write_text(json.dumps(curves))
    return folder


@pytest.fixture
def grid(tmp_path):
    rows = []
    original = {"clip_text_image_direction": 0.0, "clip_direction_consistency": 1.0,
                "ssim_edited_vs_original": 1.0, "gt_psnr_edit": 12.0, "gt_psnr_background": float("inf")}
    rows.append(R.ReportRow(Method.original("original"), None, make_evaluate(tmp_path / "e_orig", original,
                                                                           (90, 140, 60), editor=None)))
    table = {  # (DF, SA, CCI) -> per-seed C_t2i, C_dir, SSIM, PSNR_gt, PSNR_bg
        ("baseline", False, False, False): [(0.10, 0.93, 0.70, 18.0, 25.0), (0.14, 0.95, 0.72, 19.0, 26.0)],
        ("DF+SA+CCI", True, True, True): [(0.16, 0.94, 0.80, 21.0, 30.0), (0.18, 0.92, 0.84, 22.0, 31.0)],
    }
    for (label, df, sa, cci), seeds in table.items():
        for seed, (t2i, cdir, ssim, psnr_gt, psnr_bg) in enumerate(seeds):
            values = {"clip_text_image_direction": t2i, "clip_direction_consistency": cdir,
                      "ssim_edited_vs_original": ssim, "gt_psnr_edit": psnr_gt, "gt_psnr_background": psnr_bg}
            ev = make_evaluate(tmp_path / f"e_{label}_{seed}", values, (230, 230, 240 - 40 * seed))
            ed = make_edit(tmp_path / f"x_{label}_{seed}", 1.0 + seed + df)
            rows.append(R.ReportRow(Method.idu(df, sa, cci, label=label), seed, ev, ed))
    return rows, table


def test_report_contains_every_row_and_file(grid, tmp_path):
    rows, _table = grid
    out = tmp_path / "report"
    # Hand the rows over shuffled: the Original row must still come first.
    index = R.build_report([rows[3], rows[0], rows[1], rows[4], rows[2]], out,
                           title_info={"scene": "tiny", "edit": "snow"})
    assert index == out / "index.html"
    text = index.read_text()
    for name in ("table.md", "table.csv", "table.json", "grid.png", "path_strip.png", "curves/loss.png",
                 "curves/psnr.png", "curves/blend_weights.png", "curves/sa_temperature.png",
                 "curves/sa_acceptance_rate.png", "report.json"):
        assert (out / name).is_file(), name
    assert len(list((out / "videos").glob("*.mp4"))) == 5
    # Every relative reference in the HTML exists; nothing external.
    refs = re.findall(r"(?:src|href)='([^']+)'", text)
    assert refs, "the page links nothing"
    for ref in refs:
        assert not re.match(r"^[a-z]+://|^/", ref), ref
        assert (out / ref).is_file(), ref
    # Simulators are named in the title block.
    assert "InstructPix2Pix EMULATOR" in text and "NOT CLIP" in text
    assert "Original Scene" in text and "baseline" in text and "DF+SA+CCI" in text
    # CCI weights are all null in these runs (CCI off): no empty figure for them.
    assert not (out / "curves" / "cci_weights.png").exists()


def test_curves_follow_the_edit_stage_columns(tmp_path):
    curves = R.load_curves(make_edit(tmp_path / "edit", 1.0))
    steps, loss = curves["loss"]
    assert steps == list(range(0, 100, 10)) and loss[0] == 1.0
    assert "cci_weight_min" not in curves
    # Acceptances: updates with a drawn retreat are accepted, rejected, accepted, accepted.
    assert curves["sa_acceptance_rate"] == ([0, 10, 20, 30], [1.0, 0.5, 2 / 3, 0.75])


def test_table_statistics_and_best_marks(grid, tmp_path):
    rows, table = grid
    out = tmp_path / "report"
    R.build_report(rows, out, title_info={})
    doc = json.loads((out / "table.json").read_text())
    assert [r["label"] for r in doc["rows"]] == ["original", "baseline", "DF+SA+CCI"]
    assert doc["rows"][0]["dual_field"] is None and doc["rows"][2]["annealing"] is True
    full = doc["rows"][2]["metrics"]
    seeds = np.array(table[("DF+SA+CCI", True, True, True)])
    assert full["clip_text_image_direction"]["mean"] == pytest.approx(seeds[:, 0].mean())
    assert full["clip_text_image_direction"]["std"] == pytest.approx(seeds[:, 0].std(ddof=1))
    assert full["clip_text_image_direction"]["best"] is True
    # Original keeps C_dir = 1 and SSIM = 1 (identical renders): best there, as in the paper's Table 2.
    assert doc["rows"][0]["metrics"]["clip_direction_consistency"]["best"] is True
    assert doc["rows"][1]["metrics"]["clip_direction_consistency"]["best"] is False
    # inf PSNR survives as "inf" and wins its column.
    assert doc["rows"][0]["metrics"]["gt_psnr_background"]["mean"] == "inf"
    assert doc["rows"][0]["metrics"]["gt_psnr_background"]["best"] is True
    assert [c["encoder"] for c in doc["columns"] if c["name"] == "clip_text_image_direction"] == ["proxy"]
    markdown = (out / "table.md").read_text()
    assert "| Original Scene |  |  |  | - |" in markdown
    assert "| baseline | ✗ | ✗ | ✗ | 0, 1 |" in markdown
    assert "**0.1700 ± 0.0141**" in markdown           # C_t2i of the full model: mean ± std, bold
    assert "C_t2i ↑ [proxy]" in markdown
    with open(out / "table.csv") as handle:
        records = list(csv.DictReader(handle))
    assert [r["variant"] for r in records] == ["original", "baseline", "DF+SA+CCI"]
    assert float(records[1]["gt_psnr_edit_mean"]) == pytest.approx(18.5)
    assert records[2]["gt_psnr_edit_best"] == "1"


def test_lower_is_better_column_marks_the_minimum(grid, tmp_path, monkeypatch):
    rows, _ = grid
    info = M.METRICS["gt_psnr_edit"]
    monkeypatch.setitem(M.METRICS, "gt_psnr_edit", M.MetricInfo(info.symbol, False, False, info.summary))
    monkeypatch.setattr(R.tables, "METRICS", M.METRICS)
    R.build_report(rows, tmp_path / "r", title_info={})
    doc = json.loads((tmp_path / "r" / "table.json").read_text())
    assert [r["metrics"]["gt_psnr_edit"]["best"] for r in doc["rows"]] == [True, False, False]


def test_grid_rows_are_original_gt_and_variants(grid, tmp_path):
    rows, _ = grid
    R.build_report(rows, tmp_path / "r", title_info={})
    report = json.loads((tmp_path / "r" / "report.json").read_text())
    assert report["grid_rows"] == ["Original", "GT edit", "baseline", "DF+SA+CCI"]
    assert report["path_strip_rows"] == ["Original", "baseline", "DF+SA+CCI"]


def test_report_bytes_do_not_depend_on_where_the_store_is(grid, tmp_path):
    """The same results in a store at another path give the same report, byte for byte: rows are named
    by their store key (the result folder's name), never by an absolute path."""
    rows, _ = grid
    moved = tmp_path / "elsewhere" / "store"
    moved.mkdir(parents=True)
    relocated = []
    for row in rows:
        evaluate_dir = moved / row.evaluate_dir.name
        shutil.copytree(row.evaluate_dir, evaluate_dir)
        edit_dir = None
        if row.edit_dir is not None:
            edit_dir = moved / row.edit_dir.name
            shutil.copytree(row.edit_dir, edit_dir)
        relocated.append(R.ReportRow(row.method, row.seed, evaluate_dir, edit_dir))
    R.build_report(rows, tmp_path / "a", title_info={"scene": "tiny"})
    R.build_report(relocated, tmp_path / "b", title_info={"scene": "tiny"})
    files_a = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(tmp_path / "b") for p in (tmp_path / "b").rglob("*") if p.is_file())
    assert files_a == files_b and len(files_a) > 10
    for rel in files_a:
        assert (tmp_path / "a" / rel).read_bytes() == (tmp_path / "b" / rel).read_bytes(), rel
    report = json.loads((tmp_path / "b" / "report.json").read_text())
    assert [r["evaluate_key"] for r in report["rows"]] == [r.evaluate_dir.name for r in rows]
    assert str(tmp_path) not in (tmp_path / "b" / "report.json").read_text()


def test_missing_metrics_is_a_clear_error(tmp_path):
    row = R.ReportRow(Method.idu(True, True, True, label="x"), 0, tmp_path / "nowhere")
    with pytest.raises(R.ReportError, match="metrics.json is missing"):
        R.build_report([row], tmp_path / "r", title_info={})
    with pytest.raises(R.ReportError, match="nothing to report"):
        R.build_report([], tmp_path / "r", title_info={})


def test_mixed_encoders_are_refused(tmp_path):
    values = {"clip_text_image_direction": 0.1}
    rows = [R.ReportRow(Method.idu(True, True, True, label="a"), 0, make_evaluate(tmp_path / "a", values, (1, 2, 3))),
            R.ReportRow(Method.idu(False, False, False, label="b"), 0,
                        make_evaluate(tmp_path / "b", values, (1, 2, 3), encoder="clip:ViT-B/32@abc"))]
    with pytest.raises(R.ReportError, match="mix encoders"):
        R.build_report(rows, tmp_path / "r", title_info={})


def test_lpips_columns_name_the_backbone_and_refuse_mixing(tmp_path):
    values = {"ssim_edited_vs_original": 0.8, "lpips_edited_vs_original": 0.2, "gt_lpips_edit": 0.3}
    rows = [R.ReportRow(Method.original("original"), None,
                        make_evaluate(tmp_path / "o", {**values, "lpips_edited_vs_original": 0.0}, (1, 2, 3),
                                      editor=None)),
            R.ReportRow(Method.idu(True, True, True, label="a"), 0, make_evaluate(tmp_path / "a", values, (1, 2, 3)))]
    R.build_report(rows, tmp_path / "r", title_info={})
    table = (tmp_path / "r" / "table.md").read_text()
    assert "LPIPS ↓ [lpips-v0.1:alex]" in table and "LPIPS_gt ↓ [lpips-v0.1:alex]" in table
    assert "lpips-v0.1:alex (pretrained" in (tmp_path / "r" / "index.html").read_text()
    rows.append(R.ReportRow(Method.idu(False, False, False, label="b"), 0,
                            make_evaluate(tmp_path / "b", values, (1, 2, 3), lpips="lpips-v0.1:vgg")))
    with pytest.raises(R.ReportError, match="mix LPIPS backbones"):
        R.build_report(rows, tmp_path / "r2", title_info={})
