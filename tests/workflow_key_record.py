"""The step keys of every shipped workflow, recorded from the expander before the layout move (issue 31),
and what tests/test_workflow_keys_recorded.py compares them with.

    python -m tests.workflow_key_record      # rewrites tests/data/workflow_keys.json

Run it only when the expansion is meant to change (a documented key change) or a case is added. It was
run on the commit before the experiment layer moved out of stages/, so the file is the reference the
refactored expander must reproduce; cases added since then were recorded when they were added (a rerun
reproduces the earlier ones exactly, which tests/test_workflow_keys_recorded.py checks).

Steps are recorded in the workflow's order (the order they are listed, keyed and scheduled in). Two
things are recorded per step (and per cell: label, seed, scene, edit, axis values, its evaluate step):
- `shape`: a hash of what the workflow code decides, i.e. the stage, the parameters it passes (canonical
  JSON, as the key sees them before defaults are filled in) and the shapes of its inputs by name. Equal
  shapes mean equal keys under any stage version, package version or key format, so this comparison
  survives version bumps made elsewhere.
- `key`: the real store key. It also depends on the stages' versions, defaults and package versions; the
  file records a fingerprint of those (`stages`), and the real keys are compared while it still matches.
"""
from __future__ import annotations

import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "workflow_keys.json"
NO_USER = "scenes_dir=/nonexistent"

# (workflow file stem, --set overrides): every shipped workflow, plus overrides that exercise the seeds,
# method, axis, editor and filter paths of the expander.
CASES = [
    ("ablation", []),
    ("ablation", ["seeds=[0,1,2]", "edit=blue_tent"]),
    ("ablation", ["scene=tiny", "fit.iterations=300", "edit.w_max_color=0.3"]),
    ("ablation", ["seeds=[0,1]", "methods=[\"IN2N\",\"DF\"]", "edit.w_max_color=[0.05,0.3]"]),
    ("ablation_paper", []),
    ("smoke", []),
    ("smoke", ["scenes=[\"tiny\",\"campsite\"]", "edits=\"all\"", "report_dir=reports/two"]),
    ("comparison", []),
    ("comparison", ["exclude=[]", "scenes=[\"tiny\", \"campsite\"]", "edits={tiny = [\"snow\"], campsite = \"all\"}",
                    "include=[{scene = \"tiny\"}, {method = \"DualNeRF\", seed = 0}]"]),
    ("comparison", ["edit.editor=[\"synthetic\",\"ip2p\"]", "methods=[\"per-frame\"]", "seeds=[0]"]),
    ("comparison", ["scenes=[\"bear\"]", "exclude=[]", "evaluate.path_scale=[0.25,0.5]", "fit.iterations=[100,200]"]),
    ("sweep_blend", []),
    ("sweep_blend", ["seeds=[0,1,2]"]),
    ("sweep_blend", ["methods=[\"per-frame\",\"DualNeRF\"]", "exclude=[]"]),
    ("sweep_blend", ["lambda=[0.02]", "exclude=[]", "scene.supersample=2"]),
    # Added with the workflow (after the move, so recorded from the code that added it).
    ("reconstruct", []),
    # Issue 29: the failure-mode controls (lock_in axis) and the convergence study; the ablation's cases
    # re-recorded for its 3 seeds and 2000 edit iterations (a documented key change).
    ("ablation_failure_modes", []),
    ("convergence_study", []),
]


def case_id(workflow: str, overrides: list[str]) -> str:
    return " ".join([workflow, *overrides])


def stage_fingerprints() -> dict[str, str]:
    """Per stage: the key of its default step with no inputs (version, defaults, packages, key format)."""
    import dataclasses

    from pipeline.keys import key_inputs, key_of
    from pipeline.registry import load_stage
    from stages import STAGES

    out = {}
    for name in sorted(STAGES):
        cls = load_stage(STAGES, name)
        defaults = cls.Params(**{f.name: f.default for f in dataclasses.fields(cls.Params)})
        out[name] = key_of(key_inputs(cls, defaults, {}, {}, ""))
    return out


def describe(workflow) -> dict:
    """Every step (shape, key, label) and every cell (label, seed, params, evaluate step) of a workflow."""
    import tempfile

    from pipeline.canonical import canonical_value, sha256_of
    from pipeline.dag import External, Step, compute_keys
    from pipeline.store import Store
    from stages import STAGES

    shapes: dict[int, str] = {}

    def shape(step: Step) -> str:
        if id(step) not in shapes:
            inputs = {name: (shape(src) if isinstance(src, Step) else f"external:{Path(src.path).name}")
                      for name, src in step.inputs.items() if isinstance(src, (Step, External))}
            shapes[id(step)] = sha256_of(canonical_value(
                {"stage": step.stage, "params": dict(step.params), "inputs": inputs}, where=step.label))
        return shapes[id(step)]

    with tempfile.TemporaryDirectory() as tmp:
        keyed = compute_keys(workflow.steps, registry=STAGES, store=Store(Path(tmp) / "cache"))
    # 16 hex digits (64 bits) of each hash: plenty to tell ~800 steps apart, and a smaller file.
    # In the order the workflow creates them: the order steps are listed, keyed and scheduled in.
    steps = [[step.stage, step.label, shape(step)[:16], keyed[step].key[:16]] for step in workflow.steps]
    cells = [[c.label, c.seed, c.scene, c.edit_id, [[k, v] for k, v in c.params], shape(c.evaluate)[:16],
              keyed[c.evaluate].key[:16]] for c in workflow.cells]
    return {"steps": steps, "cells": cells}


def record() -> None:
    try:
        from experiments.workflow import load_workflow
    except ImportError:                     # the code before the layout move
        from stages.workflow import load_workflow

    doc = {"stages": stage_fingerprints(), "cases": {}}
    for workflow, overrides in CASES:
        wf = load_workflow(ROOT / "workflows" / f"{workflow}.toml", [NO_USER, *overrides])
        doc["cases"][case_id(workflow, overrides)] = describe(wf)
    lines = ["{", f' "stages": {json.dumps(doc["stages"], sort_keys=True)},', ' "cases": {']
    for n, (case, entry) in enumerate(doc["cases"].items()):
        lines.append(f"  {json.dumps(case)}: {{")
        for part in ("steps", "cells"):
            rows = [f"   {json.dumps(row)}" for row in entry[part]]
            lines += [f'   "{part}": [', ",\n".join(rows), "   ]" + ("," if part == "steps" else "")]
        lines.append("  }" + ("," if n < len(doc["cases"]) - 1 else ""))
    lines += [" }", "}"]
    DATA.write_text("\n".join(lines) + "\n")
    print(f"wrote {DATA}: {len(doc['cases'])} cases, "
          f"{sum(len(c['steps']) for c in doc['cases'].values())} steps")


if __name__ == "__main__":
    record()
