"""The editing loop's checkpoint leaves the frozen f_S out (it is rebuilt from the fit) and still resumes
exactly."""
import torch

from tests.test_edit_idu import make_idu, small  # noqa: F401  (fixture)


def test_dual_field_checkpoint_omits_the_static_field_and_resumes_exactly(small, tmp_path):  # noqa: F811
    full = make_idu(small, iterations=20, edit_rate=5)
    full.run()
    first = make_idu(small, iterations=20, edit_rate=5)
    first.run(until=10)
    first.save_state(tmp_path)
    saved = torch.load(tmp_path / "state.pt", weights_only=True)["trainer"]["model"]
    assert saved and not any(k.startswith("static_field.") for k in saved)
    assert any(k.startswith("dynamic_field.") for k in saved)
    resumed = make_idu(small, iterations=20, edit_rate=5)
    resumed.load_state(tmp_path)
    resumed.run()
    for (name, a), (_, b) in zip(full.model.state_dict().items(), resumed.model.state_dict().items()):
        assert torch.equal(a, b), name
