"""The shipped single-scene workflows keep their step keys across workflow-code changes: a cached
ablation is reused, not recomputed. The pinned keys (tests/data/pinned_workflow_keys.json) were computed
on the code before the grid model (issue 12), with package versions fixed to "pinned" so the file does
not depend on the installed environment. Regenerate them only together with a stage version bump."""
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PINNED = json.loads((ROOT / "tests" / "data" / "pinned_workflow_keys.json").read_text())


@pytest.mark.parametrize("case", sorted(PINNED))
def test_shipped_workflow_keys_are_unchanged(case, tmp_path, monkeypatch):
    from pipeline import keys
    from pipeline.dag import compute_keys
    from pipeline.store import Store
    from stages import STAGES
    from stages.workflow import load_workflow

    monkeypatch.setattr(keys, "package_version", lambda name: "pinned")
    name, *overrides = case.split(" ")
    wf = load_workflow(ROOT / "workflows" / f"{name}.toml", ["scenes_dir=/nonexistent", *overrides])
    keyed = compute_keys(wf.steps, registry=STAGES, store=Store(tmp_path / "cache"))
    found: dict[str, list] = {}
    for k in keyed.values():
        found.setdefault(k.step.stage, []).append(k.key)
    expected = PINNED[case]
    for stage in ("scene", "preprocess", "fit", "edit", "evaluate"):
        assert sorted(found.get(stage, [])) == expected[stage], f"{case}: {stage} keys changed"
    cells = sorted([c.label, c.seed, keyed[c.evaluate].key] for c in wf.cells)
    assert cells == expected["cells"]
