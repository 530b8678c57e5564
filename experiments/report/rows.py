"""The report's input: one `ReportRow` per evaluated result, its metrics.json, and the rows' labels."""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

from dualnerf.metrics import METRICS_FORMAT, METRICS_VERSION, parse_json_value
from experiments.methods import Method
from stages import layout


class ReportError(ValueError):
    """A report input that cannot be used; the message names the folder/file and what to do."""

    user_error = True        # the CLI prints the message and exits 2 (pipeline.errors)


@dataclass(frozen=True)
class ReportRow:
    """One evaluated result: the method that produced it (experiments.methods; the unedited scene's
    row is Method.original()), its seed and result folders, its scene edit and parameter-axis values."""

    method: Method
    seed: int | None
    evaluate_dir: Path
    edit_dir: Path | None = None
    scene: str = ""
    edit: str = ""                     # the scene edit id
    params: tuple = ()                 # parameter-axis values of this row: ((axis name, value), ...)

    @property
    def label(self) -> str:
        return self.method.label

    @property
    def is_original(self) -> bool:
        return self.method.is_original

    @property
    def method_key(self) -> tuple:
        """What makes a table row: the method and the parameter-axis values."""
        return (self.method, tuple(self.params))


def load_metrics(evaluate_dir: Path) -> dict:
    """Read and check an evaluate result's metrics.json."""
    path = Path(evaluate_dir) / layout.METRICS
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise ReportError(f"{path} is missing: {evaluate_dir} is not a finished evaluate result; "
                          f"rerun the workflow (dualnerf run) before building the report.") from None
    except json.JSONDecodeError as err:
        raise ReportError(f"{path} is not valid JSON ({err}); verify the cache (dualnerf cache verify).") from None
    if doc.get("format") != METRICS_FORMAT or doc.get("version") != METRICS_VERSION:
        raise ReportError(f"{path}: expected format {METRICS_FORMAT} v{METRICS_VERSION}, got "
                          f"{doc.get('format')} v{doc.get('version')}; rerun the evaluate stage.")
    return doc


def metric_value(entry: dict | None) -> float:
    """A metrics.json value as a float: null -> nan, the string "inf" -> inf."""
    return math.nan if entry is None else parse_json_value(entry.get("value"))


def row_key(row) -> tuple:
    """What makes a table row: the method label and the parameter-axis values (ReportRow or TableRow)."""
    return (row.label, tuple(row.params))


def display_label(label: str, params: tuple, *, original: bool = False) -> str:
    text = "Original Scene" if original else label
    return text + (" [" + ", ".join(f"{k}={v}" for k, v in params) + "]" if params else "")


def scene_edits(rows) -> list[tuple[str, str]]:
    """The distinct (scene, edit) pairs of the rows, in first-seen order."""
    return list(dict.fromkeys((row.scene, row.edit) for row in rows))


def slug(text: str, empty: str = "row") -> str:
    """`text` as a file name: runs of anything but letters, digits, '_', '.', '-' become '_'."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_") or empty
