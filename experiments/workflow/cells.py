"""What a workflow expands to: its steps and its cells (one report row each)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from experiments.methods import Method
from pipeline.dag import Step
from pipeline.errors import UserError
from pipeline.grid import format_value


class WorkflowError(UserError):
    """A workflow file or override that cannot be used; the message names the file and the field."""


@dataclass(frozen=True)
class Cell:
    """One report row: its method, the evaluate step and, for edited rows, the seed and the step that
    edited (`edit` for IDU methods, `perframe` for the per-frame baseline).

    `params` are the parameter-axis values this row's steps read, as (axis name, value) pairs."""

    method: Method
    evaluate: Step
    seed: int | None = None
    edit: Step | None = None
    scene: str = ""
    edit_id: str = ""
    params: tuple = ()
    perframe: Step | None = None

    @property
    def label(self) -> str:
        """The method's label ("Original scene" for the unedited row)."""
        return self.method.label

    @property
    def is_original(self) -> bool:
        return self.method.is_original

    def describe(self) -> str:
        parts = [f"scene={self.scene}", f"edit={self.edit_id}", f"method={self.label}"]
        parts += [] if self.seed is None else [f"seed={self.seed}"]
        parts += [f"{k}={format_value(v)}" for k, v in self.params]
        return " ".join(parts)


@dataclass
class Workflow:
    name: str
    path: Path
    scene_name: str               # the scene, or "<n>-scenes" for a grid over several
    scene_origin: str             # "procedural" or the user folder used (first scene)
    edit_id: str                  # the edit of the first cell
    instruction: str
    source_caption: str
    target_caption: str
    steps: list[Step]
    cells: list[Cell]
    report_dir: Path
    settings: dict[str, Any] = field(default_factory=dict)
    scenes: list[str] = field(default_factory=list)
    axes: list[tuple[str, int]] = field(default_factory=list)    # (axis name, number of values)
