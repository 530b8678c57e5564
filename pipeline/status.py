"""Per-step state of a DAG from the store, the leases and the run records (for `dualnerf status`).

done     published in the store
running  a live lease; progress from the step's scratch/progress.json
partial  not running, checkpoints from an earlier attempt exist (a rerun resumes)
failed   not published and the latest run record for the key says failed (with error and log path)
pending  none of the above
"""
from __future__ import annotations

import json
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from pipeline.context import PROGRESS_FILE
from pipeline.dag import Step, compute_keys, step_state
from pipeline.runrecord import read_runs


@dataclass(frozen=True)
class StepStatus:
    label: str
    stage: str
    key: str
    state: str
    detail: str = ""


def _progress_text(path: Path) -> str:
    try:
        progress = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return ""
    text = f"{progress['desc']} {progress['done']}/{progress['total']}"
    if progress.get("eta_s") is not None:
        text += f", eta {progress['eta_s']:.0f}s"
    age = time.time() - progress.get("updated", time.time())
    if age > 60:
        text += f" (last update {age:.0f}s ago)"
    return text


def workflow_status(steps: Sequence[Step], *, registry: Mapping[str, str], store,
                    runs_dir: Path) -> list[StepStatus]:
    keyed = compute_keys(steps, registry=registry, store=store)
    latest: dict[str, dict] = {}
    for record in read_runs(runs_dir, store.registered_run_files()):   # oldest first: later runs win
        for entry in record.get("steps", []):
            latest[entry["key"]] = entry
    out = []
    for k in keyed.values():
        state = step_state(store, k.key)
        detail = ""
        if state == "cached":
            state = "done"
        elif state == "running":
            holder = store.lease_holder(k.key)
            detail = _progress_text(store.scratch_path(k.key) / PROGRESS_FILE)
            detail += f" [{holder.host} pid {holder.pid}]" if holder else ""
        else:
            entry = latest.get(k.key)
            if entry is not None and entry.get("status") == "failed":
                state, detail = "failed", f"{entry.get('error')} (log: {entry.get('log')})"
            elif state == "partial":
                detail = _progress_text(store.scratch_path(k.key) / PROGRESS_FILE)
        out.append(StepStatus(k.label, k.stage_cls.name, k.key, state, detail.strip()))
    return out
