"""The editing loop (dualnerf.idu) on a downscaled `tiny` scene: toggles, SA retreats, CCI weights,
exact resume, and movement toward the ground-truth edit."""
import numpy as np
import pytest
import torch

from dualnerf.idu import IDUConfig, IterativeDatasetUpdate

SNOW = "snow"
SMALL = 40              # long side of the test dataset (40x30): renders cost ~1200 rays


def build_small_edit_inputs(tmp_path_factory, tiny_scene):
    """A 40x30 dataset of `tiny` (with scene.toml and gt/edits/) and a fitted static field, built once per
    test session in a shared folder (several test modules use it)."""
    from dualnerf.cameras import Cameras
    from dualnerf.dataset import load_dataset
    from dualnerf.fields import FieldConfig, RadianceField
    from dualnerf.io import PreprocessConfig, preprocess
    from dualnerf.model import load_model, save_model
    from dualnerf.training import RayTrainer, TrainConfig

    root = tmp_path_factory.getbasetemp() / "edit_small"
    data_dir, fit_dir = root / "dataset", root / "fit"
    if not (fit_dir / "model" / "model.json").exists():
        preprocess(tiny_scene, data_dir, PreprocessConfig(method="nerfstudio", max_size=SMALL))
        dataset = load_dataset(data_dir)
        config = FieldConfig(grid_resolutions=(8, 16, 32, 64), hidden_width=32, samples_per_ray=40,
                             occupancy_resolution=32)
        generator = torch.Generator().manual_seed(0)
        field = RadianceField(config, generator=generator)
        trainer = RayTrainer(field, torch.from_numpy(dataset.images).float() / 255, Cameras.from_dataset(dataset),
                             TrainConfig(rays_per_batch=512), generator, dataset.indices("train"))
        for step in range(300):
            trainer.step(step)
        save_model(fit_dir / "model", field)
    return data_dir, fit_dir, load_dataset(data_dir), load_model(fit_dir / "model")


@pytest.fixture(scope="module")
def small(tmp_path_factory, tiny_scene):
    return build_small_edit_inputs(tmp_path_factory, tiny_scene)


def make_idu(small, emulator=None, encoder=True, **overrides):
    from dualnerf.editors.emulator import EmulatorConfig, InstructPix2PixEmulator
    from dualnerf.encoders import load_encoder
    from dualnerf.encoders.vocabulary import proxy_vocabulary
    from dualnerf.scenes import load_scene_spec

    data_dir, _, dataset, static = small
    instruction = load_scene_spec(data_dir).edit(SNOW).instruction
    train = dataset.indices("train")
    editor = InstructPix2PixEmulator.from_scene_folder(data_dir, SNOW, instruction,
                                                       [dataset.names[i] for i in train], dataset.images[train],
                                                       emulator or EmulatorConfig())
    enc = None
    if encoder:
        enc = load_encoder("proxy", vocabulary=proxy_vocabulary(data_dir, SNOW, dataset.names, dataset.images))
    config = IDUConfig(**{"iterations": 20, "edit_rate": 5, "edit_count": 1, "rays_per_batch": 256,
                          **overrides})
    return IterativeDatasetUpdate(config, static, dataset, editor, instruction, encoder=enc)


def _params(module):
    return {k: v.detach().clone() for k, v in module.named_parameters()}


def test_dual_field_trains_only_the_dynamic_field(small):
    idu = make_idu(small, dual_field=True, annealing=False, consistency=False, iterations=12)
    static_before = _params(idu.model.static_field)
    dynamic_before = _params(idu.model.dynamic_field)
    idu.run()
    for name, value in _params(idu.model.static_field).items():
        assert torch.equal(value, static_before[name]), name               # f_S frozen, bit for bit
    changed = [n for n, v in _params(idu.model.dynamic_field).items() if not torch.equal(v, dynamic_before[n])]
    assert len(changed) == len(dynamic_before)                              # every f_D tensor trained
    assert idu.curves["blend_color"][-1] == pytest.approx(0.1 * np.tanh(0.005 * 11))


def test_single_field_baseline_trains_all_parameters(small):
    idu = make_idu(small, dual_field=False, annealing=False, consistency=False, iterations=12)
    before = _params(idu.model)
    assert all(p.requires_grad for p in idu.model.parameters())
    idu.run()
    after = _params(idu.model)
    assert all(not torch.equal(after[n], before[n]) for n in before)
    assert idu.blend_at(5) is None and set(idu.curves["blend_color"]) == {0.0}


@pytest.mark.parametrize("dual_field", [True, False])
def test_retreat_interpolates_toward_the_static_field(small, dual_field):
    from dualnerf.rendering import render_view

    _, _, dataset, static = small
    idu = make_idu(small, dual_field=dual_field, annealing=False, consistency=False, iterations=30)
    idu.run()
    view, t = idu.train_views[0], 29
    static_render = render_view(static, dataset.c2w[view], dataset.intrinsics[view], dataset.width,
                                dataset.height, float(dataset.near[view]), float(dataset.far[view])).numpy()
    latest = idu.render(view, t, 1.0)
    retreated = {g: idu.render(view, t, g) for g in (0.0, 0.5)}
    moved = np.abs(latest - static_render).mean()
    assert moved > 1e-3                                                             # the model moved
    # gamma = 0 has f_S's features exactly (only the sampling follows the edited model's occupancy grid),
    # gamma = 0.5 lands in between
    d0 = np.abs(retreated[0.0] - static_render).mean()
    d_half_static = np.abs(retreated[0.5] - static_render).mean()
    d_half_latest = np.abs(retreated[0.5] - latest).mean()
    print(f"mean |render - f_S|: latest {moved:.4f}, gamma=0.5 {d_half_static:.4f}, gamma=0 {d0:.4f}")
    assert d0 < 0.25 * moved
    assert d0 < d_half_static < moved and d_half_latest < moved


class RecordingEditor:
    """Wraps an editor; records the render it was given and the latest model's render at that moment."""

    def __init__(self, inner):
        self.inner, self.calls, self.idu = inner, [], None
        self.identity, self.last_details = inner.identity, {}

    def edit(self, render, original, instruction, seed, step):
        view = next(i for i in self.idu.train_views if np.array_equal(self.idu.originals[i], original))
        self.calls.append((step, np.array(render), self.idu.render(view, step, 1.0)))
        out = self.inner.edit(render, original, instruction, seed, step)
        self.last_details = self.inner.last_details
        return out


@pytest.mark.slow
@pytest.mark.parametrize("annealing", [False, True])
def test_annealing_toggle_controls_retreated_renders(small, annealing):
    idu = make_idu(small, dual_field=True, annealing=annealing, consistency=False, iterations=120, edit_rate=4)
    idu.editor = RecordingEditor(idu.editor)
    idu.editor.idu = idu
    idu.run()
    log = idu.updates
    assert len(log) == 30
    if not annealing:
        assert all(u["gamma"] is None and u["render_retreat"] == 1.0 for u in log)
    else:
        assert all((u["render_retreat"] == u["gamma"]) == u["accepted"] or u["gamma"] == 1.0 for u in log)
        assert 0 < sum(u["accepted"] for u in log) < len(log)
    for u, (step, given, latest) in zip(log, idu.editor.calls):
        assert step == u["iteration"]
        if u["render_retreat"] == 1.0:
            np.testing.assert_array_equal(given, latest)          # rendered from the latest model
        elif step >= 40 and u["render_retreat"] < 0.8:
            assert np.abs(given - latest).max() > 1e-3            # rendered from a retreated model


def test_consistency_off_is_uniform_and_on_downweights_failures(small):
    from dualnerf.editors.emulator import EmulatorConfig

    off = make_idu(small, consistency=False, annealing=False, iterations=6)
    off.run()
    assert off.view_weights() is None and set(off.curves["cci_weight_min"]) == {None}
    assert all(u["score"] is not None and u["weight"] is None for u in off.updates)   # S logged, not used

    on = make_idu(small, consistency=True, annealing=False, iterations=1, edit_rate=1,
                  emulator=EmulatorConfig(failure_rate=0.3))
    n_views = len(on.train_views)
    failed, weights = [], []
    for t in range(3 * n_views):                     # three rounds over the views, no training needed
        on.dataset_update(t)
        u = on.updates[-1]
        failed.append(u["editor"]["failed"])
        weights.append(u["weight"])
    failed, weights = np.array(failed), np.array(weights)
    assert on.view_weights()[on.train_views].mean() == pytest.approx(1.0)
    below = weights < 1.0
    recall = below[failed].mean()                    # failures that got a below-average weight
    precision = failed[below].mean()                 # below-average weights that are failures
    print(f"CCI proxy: {failed.sum()} failures of {len(failed)}; recall {recall:.2f} precision {precision:.2f}")
    assert recall >= 0.6
    assert precision > failed.mean() + 0.1
    assert weights[failed].mean() < weights[~failed].mean()


def test_resume_from_saved_state_is_exact(small, tmp_path):
    kwargs = {"iterations": 30, "edit_rate": 5, "edit_count": 2}
    full = make_idu(small, **kwargs)
    full.run()
    first = make_idu(small, **kwargs)
    first.run(until=15)
    first.save_state(tmp_path)
    resumed = make_idu(small, **kwargs)
    resumed.load_state(tmp_path)
    resumed.run()
    for (name, a), (_, b) in zip(full.model.state_dict().items(), resumed.model.state_dict().items()):
        assert torch.equal(a, b), name
    np.testing.assert_array_equal(full.images, resumed.images)
    assert full.updates == resumed.updates and full.curves == resumed.curves


def test_a_shorter_run_is_the_start_of_a_longer_one(small):
    # The preset's length was chosen by cutting longer runs' convergence curves (stages/edit.py): that
    # holds only if nothing before iteration N depends on the run's length (blend, temperature and
    # learning-rate schedules are functions of the iteration; so are the editor's and SA's draws).
    kwargs = {"edit_rate": 5, "edit_count": 1, "annealing": True, "consistency": True}
    short = make_idu(small, iterations=20, **kwargs)
    short.run()
    long = make_idu(small, iterations=35, **kwargs)
    long.run(until=20)
    for (name, a), (_, b) in zip(short.model.state_dict().items(), long.model.state_dict().items()):
        assert torch.equal(a, b), name
    np.testing.assert_array_equal(short.images, long.images)
    assert short.updates == long.updates and short.curves == long.curves
    assert len(short.updates) == 4


@pytest.mark.slow
def test_snow_edit_moves_the_model_toward_the_ground_truth(small):
    from dualnerf.rendering import render_view
    from dualnerf.scenes import load_gt_edit

    data_dir, _, dataset, static = small
    views = dataset.indices("train")
    gt = np.stack([load_gt_edit(data_dir, SNOW, dataset.names[i])[0] for i in views]) / 255.0

    def psnr_to_gt(model, blend):
        renders = np.stack([render_view(model, dataset.c2w[i], dataset.intrinsics[i], dataset.width,
                                        dataset.height, float(dataset.near[i]), float(dataset.far[i]),
                                        blend=blend).numpy() for i in views])
        return -10 * np.log10(np.mean((renders - gt) ** 2))

    idu = make_idu(small, iterations=150, edit_rate=5, edit_count=1, rays_per_batch=512)
    idu.run()
    model = idu.final_model()
    before, after = psnr_to_gt(static, None), psnr_to_gt(model, model.render_blend)
    print(f"PSNR to the ground-truth snow edit: f_S {before:.2f} dB -> DualNeRF {after:.2f} dB")
    assert after > before + 4.0


def test_samples_per_ray_sets_training_and_view_update_samples(small, monkeypatch):
    # The CPU preset trains and renders view updates at fewer samples than the fitted field's own: every
    # training ray and every rendered ray evaluates at most that many; 0 keeps the field's counts.
    from dualnerf import rendering

    _, _, _, static = small
    counts = []
    original = rendering.render_rays

    def counting(model, origins, *args, samples_per_ray=None, **kwargs):
        out = original(model, origins, *args, samples_per_ray=samples_per_ray, **kwargs)
        counts.append((kwargs.get("generator") is not None, origins.shape[0], out["evaluated"], samples_per_ray))
        return out

    monkeypatch.setattr(rendering, "render_rays", counting)
    monkeypatch.setattr("dualnerf.training.render_rays", counting)
    for setting, train_samples, render_samples in ((6, 6, 6), (0, static.config.samples_per_ray,
                                                               static.config.render_samples_per_ray)):
        counts.clear()
        idu = make_idu(small, dual_field=True, annealing=False, consistency=False, iterations=3, edit_rate=5,
                       samples_per_ray=setting)
        idu.run()
        training = [c for c in counts if c[0]]
        renders = [c for c in counts if not c[0]]
        assert len(training) == 3 and renders                       # 3 steps, 1 view update
        assert all(c[3] == (setting or None) for c in training)
        assert all(evaluated <= rays * train_samples for _, rays, evaluated, _ in training)
        assert all(evaluated <= rays * render_samples for _, rays, evaluated, _ in renders)
        assert sum(e for _, _, e, _ in renders) > sum(r for _, r, _, _ in renders) * min(render_samples, 6) / 2
    with pytest.raises(Exception, match="samples_per_ray"):
        IDUConfig(samples_per_ray=1)
