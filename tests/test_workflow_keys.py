"""The shipped single-scene workflows keep their step keys across the grid model (issue 12): a cached
ablation is reused, not recomputed. The reference is the pre-grid expansion, frozen in
tests/legacy_workflow.py; both are keyed with the current stages, so a stage version bump elsewhere
changes both sides alike and this test still isolates the workflow code."""
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CASES = [("ablation", []), ("ablation", ["seeds=[0,1,2]", "edit=blue_tent"]),
         ("ablation", ["scene=tiny", "fit.iterations=300", "edit.w_max_color=0.3"]),
         ("smoke", []), ("ablation_paper", [])]


def _as_variants(workflow: str, folder) -> Path:
    """The shipped workflow in the older syntax the frozen expander reads: `methods` (issue 31) as
    `variants` rows."""
    import tomllib

    from experiments.methods import Method

    path = ROOT / "workflows" / f"{workflow}.toml"
    text = path.read_text()
    names = tomllib.loads(text)["workflow"]["methods"]
    rows = ", ".join("[" + ", ".join(str(f).lower() for f in Method.parse(n).flags) + "]" for n in names)
    lines = [f"variants = [{rows}]" if line.startswith("methods =") else line for line in text.splitlines()]
    copy = folder / path.name
    copy.write_text("\n".join(lines) + "\n")
    return copy


def _keys(load, path, overrides, store):
    from pipeline.dag import compute_keys
    from stages import STAGES

    wf = load(path, ["scenes_dir=/nonexistent", *overrides])
    keyed = compute_keys(wf.steps, registry=STAGES, store=store)
    by_stage: dict[str, list] = {}
    for k in keyed.values():
        by_stage.setdefault(k.step.stage, []).append((k.key, k.step.label))
    cells = sorted((c.label, -1 if c.seed is None else c.seed, keyed[c.evaluate].key) for c in wf.cells)
    return {s: sorted(v) for s, v in by_stage.items()}, cells


@pytest.mark.parametrize("workflow, overrides", CASES, ids=[" ".join([w, *o]) for w, o in CASES])
def test_single_scene_workflows_keep_their_keys(workflow, overrides, tmp_path):
    from experiments.workflow import load_workflow
    from pipeline.store import Store
    from tests.legacy_workflow import load_workflow as load_legacy

    store = Store(tmp_path / "cache")
    old_steps, old_cells = _keys(load_legacy, _as_variants(workflow, tmp_path), overrides, store)
    new_steps, new_cells = _keys(load_workflow, ROOT / "workflows" / f"{workflow}.toml", overrides, store)
    assert new_steps == old_steps          # same keys, and the same step labels in run records and logs
    assert new_cells == old_cells          # same rows, same labels, same evaluate keys
    assert len(old_steps["fit"]) == 1 and len(old_steps["edit"]) == len(old_cells) - 1
