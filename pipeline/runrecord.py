"""Run records: `runs/<run>/run.json`, rewritten atomically as steps change state, plus `logs/`.

run.json = {format, run, cache, started, updated, finished, status, steps: [{label, stage, key,
inputs: {name: {"step": label, "key": key} | {"external": path}}, params, status, error, user_error,
log, started, finished, duration_s}]}. Step status is one of pending, running, done, cached,
failed, skipped (an upstream step failed) or interrupted. gc treats every key named here as a root.
"""
from __future__ import annotations

import json
import re
import time
from pathlib import Path
from typing import Any

from pipeline.canonical import canonical_value
from pipeline.hashing import write_json_atomic

RUN_FILE = "run.json"


def safe_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._=-]+", "_", text).strip("._") or "step"


class RunRecord:
    def __init__(self, run_dir: Path, cache_root: Path):
        self.dir = Path(run_dir)
        self.path = self.dir / RUN_FILE
        self.logs = self.dir / "logs"
        self.data: dict[str, Any] = {"format": 1, "run": self.dir.name, "cache": str(cache_root),
                                     "started": time.time(), "finished": None, "status": "running",
                                     "steps": []}

    def add_step(self, *, label: str, stage: str, key: str, inputs: dict, params: dict, log: Path) -> int:
        self.data["steps"].append({"label": label, "stage": stage, "key": key, "inputs": inputs,
                                   "params": canonical_value(params), "status": "pending", "error": None,
                                   "user_error": False, "log": str(log), "started": None, "finished": None,
                                   "duration_s": None})
        return len(self.data["steps"]) - 1

    def update_key(self, key: str, **fields: Any) -> None:
        for entry in self.data["steps"]:
            if entry["key"] == key:
                entry.update(fields)

    def save(self) -> None:
        self.dir.mkdir(parents=True, exist_ok=True)
        self.data["updated"] = time.time()
        write_json_atomic(self.path, self.data, indent=None)   # rewritten at every state change: keep it fast


def read_runs(runs_dir: Path, extra_files: list[Path] = ()) -> list[dict[str, Any]]:
    """Every readable run record under `runs_dir` (plus `extra_files`), oldest first."""
    paths = set(Path(runs_dir).glob(f"*/{RUN_FILE}")) if Path(runs_dir).is_dir() else set()
    paths |= {Path(p) for p in extra_files}
    records = []
    for path in paths:
        try:
            records.append(json.loads(path.read_text(encoding="utf-8")))
        except (OSError, ValueError):
            continue
    return sorted(records, key=lambda r: r.get("started") or 0)


def referenced_keys(runs_dir: Path, extra_files: list[Path] = ()) -> set[str]:
    """gc roots: every key named by a run record under `runs_dir` or in `extra_files`."""
    return {step["key"] for record in read_runs(runs_dir, extra_files) for step in record.get("steps", [])}
