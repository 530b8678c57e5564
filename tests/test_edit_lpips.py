"""The editing loop with the LPIPS patch loss on (the edit stage's default): exact resume, and the LPIPS
term really enters the loss. The 40x30 test dataset takes VGG16's 16x16 patches (AlexNet needs 31)."""
import numpy as np
import pytest
import torch

from tests.test_edit_idu import build_small_edit_inputs, make_idu

LPIPS_ON = {"lpips_weight": 1.0, "lpips_net": "vgg", "patch_size": 16, "patch_share": 0.5,
            "iterations": 20, "edit_rate": 5, "edit_count": 1}


@pytest.fixture(scope="module")
def small(tmp_path_factory, tiny_scene):
    return build_small_edit_inputs(tmp_path_factory, tiny_scene)


def test_idu_with_lpips_resumes_exactly(small, tmp_path):
    full = make_idu(small, **LPIPS_ON)
    full.run()
    assert full.trainer.lpips is not None and full.trainer.patches == 1
    first = make_idu(small, **LPIPS_ON)
    first.run(until=10)
    first.save_state(tmp_path)
    resumed = make_idu(small, **LPIPS_ON)
    resumed.load_state(tmp_path)
    resumed.run()
    for (name, a), (_, b) in zip(full.model.state_dict().items(), resumed.model.state_dict().items()):
        assert torch.equal(a, b), name
    np.testing.assert_array_equal(full.images, resumed.images)
    assert full.curves == resumed.curves


def test_lpips_term_changes_the_edit(small):
    on = make_idu(small, **LPIPS_ON)
    on.run()
    off = make_idu(small, **{**LPIPS_ON, "lpips_weight": 0.0})
    off.run()
    # The loss with LPIPS holds a positive LPIPS term on top of an RGB loss of the same order.
    assert min(on.curves["loss"]) > 0 and np.mean(on.curves["loss"]) > 2 * np.mean(off.curves["loss"])
    a, b = on.model.state_dict(), off.model.state_dict()
    assert any(not torch.equal(a[k], b[k]) for k in a)
