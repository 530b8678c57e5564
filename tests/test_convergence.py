"""The edit stage's convergence probe (dualnerf.convergence) and the report's convergence figure."""
import math

import numpy as np
import pytest
import torch

from dualnerf.cameras import pixel_rays
from dualnerf.convergence import ConvergenceProbe, downsample, masked_psnr, probe_for_scene_edit
from experiments.methods import Method
from experiments.report.convergence import remaining_change
from tests.test_edit_idu import SNOW, make_idu, small  # noqa: F401  (fixture)


def test_downsample_is_the_block_mean_and_masked_psnr_the_closed_form():
    image = np.arange(4 * 6 * 1, dtype=np.float64).reshape(4, 6, 1)
    small_image = downsample(image, 2)
    assert small_image.shape == (2, 3, 1)
    assert small_image[0, 0, 0] == np.mean([0, 1, 6, 7]) and small_image[1, 2, 0] == np.mean([16, 17, 22, 23])
    a, b = np.zeros((2, 2, 3)), np.full((2, 2, 3), 0.1)
    mask = np.array([[True, False], [False, False]])
    b[1, 1] = 0.9                                                       # outside the mask: ignored
    assert masked_psnr(a, b, mask) == pytest.approx(20.0)              # -10 log10(0.01)
    assert math.isnan(masked_psnr(a, b, np.zeros((2, 2), bool)))


def test_probe_cameras_cast_the_rays_through_the_centres_of_the_full_pixel_blocks():
    c2w = np.eye(4)[None]
    k = np.array([[100.0, 90.0, 64.0, 48.0]])
    image = np.zeros((1, 96, 128, 3), np.uint8)
    probe = ConvergenceProbe([0], c2w, k, 128, 96, [0.1], [5.0], image, np.zeros((1, 96, 128), bool), image,
                             scale=0.5)
    assert (probe.width, probe.height) == (64, 48)
    c2w_t = torch.as_tensor(c2w, dtype=torch.float32)
    u_small, v_small = torch.tensor([0.0, 13.0, 63.0]), torch.tensor([0.0, 7.0, 47.0])
    _, small_dirs = pixel_rays(c2w_t.expand(3, 4, 4), torch.as_tensor(probe.intrinsics[0], dtype=torch.float32)
                               .expand(3, 4), u_small, v_small)
    # The centre of the 2x2 block of full pixels (2u, 2u+1) is at full-pixel coordinate 2u + 0.5.
    _, full_dirs = pixel_rays(c2w_t.expand(3, 4, 4), torch.as_tensor(k, dtype=torch.float32).expand(3, 4),
                              2 * u_small + 0.5, 2 * v_small + 0.5)
    torch.testing.assert_close(small_dirs, full_dirs)


def test_probing_does_not_change_the_run_and_resumes_exactly(small, tmp_path):  # noqa: F811
    data_dir, _, dataset, _ = small
    probe = probe_for_scene_edit(data_dir, dataset, SNOW, n_views=2, scale=0.5, every=10)
    assert probe is not None and len(probe.views) == 2
    plain = make_idu(small, iterations=25, edit_rate=5)
    plain.run()
    probed = make_idu(small, iterations=25, edit_rate=5)
    probed.probe = probe
    probed.run()
    for (name, a), (_, b) in zip(plain.model.state_dict().items(), probed.model.state_dict().items()):
        assert torch.equal(a, b), name
    conv = probed.curves_json()["convergence"]
    assert conv["iteration"] == [0, 10, 20, 25] and all(np.isfinite(conv["psnr_in"]))
    assert plain.curves_json()["convergence"] is None
    first = make_idu(small, iterations=25, edit_rate=5)
    first.probe = probe
    first.run(until=15)
    first.save_state(tmp_path)
    resumed = make_idu(small, iterations=25, edit_rate=5)
    resumed.probe = probe
    resumed.load_state(tmp_path)
    resumed.run()
    assert resumed.curves_json()["convergence"] == conv


def test_remaining_change_recovers_a_saturating_curve_and_flags_a_straight_line():
    it = list(range(0, 1501, 100))
    saturated = [10 + 8 * (1 - math.exp(-t / 300)) for t in it]        # 5 time constants: exp(-5) left
    fit = remaining_change(it, saturated)
    assert fit["plateau"] == pytest.approx(18.0, abs=1e-3)
    assert fit["share"] == pytest.approx(math.exp(-5), abs=1e-3)
    assert fit["remaining"] == pytest.approx(8 * math.exp(-5), abs=1e-2)
    young = [10 + 8 * (1 - math.exp(-t / 1500)) for t in it]           # one time constant: 37% left
    assert remaining_change(it, young)["share"] == pytest.approx(math.exp(-1), abs=1e-2)
    line = remaining_change(it, [10 + t / 100 for t in it])
    assert line["share"] > 0.8 and line["plateau"] > 40                # no plateau in sight
    falling = remaining_change(it, [29 - 11 * (1 - math.exp(-t / 200)) for t in it])
    assert falling["plateau"] == pytest.approx(18.0, abs=1e-3) and falling["share"] < 0.01
    rng = np.random.default_rng(0)
    noisy = remaining_change(it, [v + rng.normal(0, 0.2) for v in saturated])
    assert noisy["share"] < 0.1 and abs(noisy["plateau"] - 18) < 0.5
    assert remaining_change(it, [12.0] * len(it)) is None
    assert remaining_change(it[:3], saturated[:3]) is None
def test_report_draws_one_convergence_panel_per_row_with_probe_data(tmp_path):
    import json

    from experiments.report import ReportRow
    from experiments.report.convergence import write_convergence

    rows = []
    for k, label in enumerate(("baseline", "DF+SA+CCI", "Original")):
        edit_dir = tmp_path / f"edit{k}"
        edit_dir.mkdir()
        conv = None if label == "Original" else {"iteration": [0, 100, 200], "psnr_in": [12.0, 18.0, 19.0],
                                                 "psnr_out": [30.0, 29.5, 29.4], "views": [1, 2], "scale": 0.5}
        (edit_dir / "curves.json").write_text(json.dumps({"iteration": [], "convergence": conv}))
        rows.append(ReportRow(Method.idu(True, True, True, label=label), 0, tmp_path, edit_dir))

    (tmp_path / "out").mkdir(exist_ok=True)
    assert write_convergence(rows, tmp_path / "out") == ["curves/convergence.png"]
    assert (tmp_path / "out" / "curves" / "convergence.png").stat().st_size > 1000
    assert write_convergence(rows[2:], tmp_path / "out") == []


def test_convergence_summary_and_page_table(tmp_path):
    import json
    from types import SimpleNamespace

    from experiments.report.convergence import convergence_html, convergence_summary

    it = list(range(0, 2001, 100))
    rows = []
    for name, values in (("settled", [10 + 8 * (1 - math.exp(-t / 300)) for t in it]),
                         ("rising", [5 + t / 100 for t in it])):
        folder = tmp_path / name
        folder.mkdir()
        (folder / "curves.json").write_text(json.dumps({"convergence": {
            "iteration": it, "psnr_in": values, "psnr_out": [25.0] * len(it), "views": [0], "scale": 0.5}}))
        rows.append(SimpleNamespace(label=name, seed=0, edit_dir=folder))
    rows.append(SimpleNamespace(label="original", seed=None, edit_dir=None))       # no probe: left out
    settled, rising = convergence_summary(rows)
    assert settled["converged"] and settled["plateau"] == pytest.approx(18.0, abs=1e-3)
    assert settled["note"].startswith("converged")
    assert rising["converged"] is False and rising["plateau"] is None and rising["share_left"] is None
    assert "still +10.0 dB per 1000 iterations" in rising["note"]            # the line's slope: 1 dB / 100
    page = "".join(convergence_html([settled, rising]))
    assert "settled (seed 0)" in page and "18.0" in page and "no plateau in sight" in page
    assert convergence_html([]) == []
