"""The stage parameter reference, read from the stages themselves: each Params dataclass field's type,
default and source comment, whether it enters the step's key, and whether the workflow sets it.

    parameters("edit") -> [Param(stage="edit", name="dual_field", type="bool", default=True, ...), ...]
    text("edit")        what `dualnerf params edit` prints
    markdown()          docs/params.md (tests/test_params_doc.py keeps the file in sync)

The comment of a field is the comment on its line, continued by comment-only lines aligned with it, and
preceded by comment-only lines directly above the field.
"""
from __future__ import annotations

import dataclasses
import inspect
import io
import json
import textwrap
import tokenize
from dataclasses import dataclass

# Stage order for listings: the order of a workflow's DAG.
ORDER = ("scene", "preprocess", "fit", "edit", "gtviews", "perframe", "evaluate")


@dataclass(frozen=True)
class Param:
    stage: str
    name: str
    type: str
    default: object
    comment: str
    in_key: bool                  # False: non-semantic (threads, chunk sizes, checkpoint spacing)
    set_by: str = ""              # the workflow setting that decides it ("methods", "seeds", ...), if any

    @property
    def default_text(self) -> str:
        return toml_value(self.default)


def toml_value(value) -> str:
    """A default as it is written in a workflow file or after `--set`."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    return repr(value)


def stage_names() -> list[str]:
    from stages import STAGES

    return [name for name in ORDER if name in STAGES] + sorted(set(STAGES) - set(ORDER))


def stage_class(stage: str):
    from pipeline.registry import load_stage
    from stages import STAGES

    return load_stage(STAGES, stage)


def field_comments(cls: type) -> dict[str, str]:
    """{field name: its source comment} of a dataclass."""
    lines, _ = inspect.getsourcelines(cls)
    comments: dict[int, tuple[int, str, bool]] = {}      # line -> (column, text, whole line is a comment)
    for tok in tokenize.generate_tokens(io.StringIO("".join(lines)).readline):
        if tok.type == tokenize.COMMENT:
            row, col = tok.start
            alone = not lines[row - 1][:col].strip()
            comments[row] = (col, tok.string.lstrip("#").strip(), alone)
    names = {f.name for f in dataclasses.fields(cls)}
    out = {}
    for row, line in enumerate(lines, start=1):
        name = line.split(":", 1)[0].strip()
        if name not in names or line.lstrip().startswith("#"):
            continue
        indent = len(line) - len(line.lstrip())
        above, r = [], row - 1
        while r in comments and comments[r][2] and comments[r][0] == indent:
            above.insert(0, comments[r][1])
            r -= 1
        parts = above
        if row in comments and not comments[row][2]:
            column = comments[row][0]
            parts = parts + [comments[row][1]]
            r = row + 1
            while r in comments and comments[r][2] and comments[r][0] == column:
                parts.append(comments[r][1])
                r += 1
        out[name] = " ".join(p for p in parts if p)
    return out


def parameters(stage: str) -> list[Param]:
    from experiments.workflow.grid import MANAGED

    cls = stage_class(stage)
    comments = field_comments(cls.Params)
    out = []
    for f in dataclasses.fields(cls.Params):
        kind = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        out.append(Param(stage, f.name, kind, default, comments.get(f.name, ""),
                         f.name not in cls.nonsemantic_params, MANAGED.get(stage, {}).get(f.name, "")))
    return out


def _summary(stage: str) -> str:
    """The first paragraph of the stage module's docstring, less its 'Stage "x": ' prefix."""
    doc = inspect.getdoc(inspect.getmodule(stage_class(stage))) or ""
    first = doc.split("\n\n")[0].replace("\n", " ").strip()
    first = first.split(": ", 1)[1] if first.startswith("Stage ") and ": " in first else first
    return (first[:1].upper() + first[1:]).rstrip(".")


def _notes(p: Param) -> list[str]:
    return (([] if p.in_key else ["not in the key"]) +
            ([f"set by the workflow from {p.set_by}"] if p.set_by else []))


def text(stage: str, width: int = 100) -> str:
    """What `dualnerf params STAGE` prints: a header, then per parameter `stage.name = default  (type;
    notes)` and its comment, indented."""
    cls = stage_class(stage)
    lines = textwrap.wrap(f"{stage} (stage version {cls.version}): {_summary(stage)}", width=width + 6)
    for p in parameters(stage):
        notes = "; ".join([p.type, *_notes(p)])
        lines.append(f"  {stage}.{p.name} = {p.default_text}   ({notes})")
        if p.comment:
            lines += textwrap.wrap(p.comment, width=width, initial_indent="      ", subsequent_indent="      ")
    return "\n".join(lines)


def markdown() -> str:
    """docs/params.md: one table per stage."""
    intro = ("Generated by `dualnerf params --markdown` from the stages' Params dataclasses (their source "
             "comments); `tests/test_params_doc.py` fails when this file and the code disagree. Set any "
             "parameter with `--set <stage>.<param>=VALUE` or in a workflow's `[stages.<stage>]` table; a list "
             "value for a scalar parameter makes it a grid axis (docs/workflows.md).")
    legend = ("*key*: whether the value enters the step's cache key (docs/caching.md); parameters that are not "
              "in the key (threads, batch sizes of the same computation, checkpoint spacing) do not change "
              "results. *set by* names the workflow setting that decides a parameter (set it there, not here).")
    out = ["# Stage parameters", "", intro, "", legend, ""]
    for stage in stage_names():
        cls = stage_class(stage)
        out += [f"## {stage}", "", f"{_summary(stage)}. Source: `stages/{stage}.py` (stage version {cls.version}).", "",
                "| parameter | type | default | key | description |", "|---|---|---|---|---|"]
        for p in parameters(stage):
            key = "yes" if p.in_key else "no"
            note = f" *Set by the workflow from {p.set_by}.*" if p.set_by else ""
            comment = (p.comment + note).strip().replace("|", "\\|")
            out.append(f"| `{p.name}` | {p.type} | `{p.default_text}` | {key} | {comment} |")
        out.append("")
    return "\n".join(out)
