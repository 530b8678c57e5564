"""Names that become folder names, and folders that must stay inside the folder they belong to.

A name taken from a workflow or its data (a run's subject, a report folder's `{placeholder}`) is
substituted into paths; it must be a plain name so that `runs/<name>`, `reports/<name>` and the like
stay inside `runs/` and `reports/`. `confined` is the check for the composed path itself.
"""
from __future__ import annotations

import re
from pathlib import Path

from pipeline.errors import UserError

PLAIN_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")
PLAIN_NAME_RULE = ("1 to 100 characters from letters, digits, '.', '_' and '-', starting with a letter or "
                   "digit (no '/', '..', spaces)")


class PathError(UserError):
    """A name or path that would make a run read or write outside the folder it belongs to."""


def check_plain_name(value: object, what: str) -> str:
    """`value` if it is a plain name; else a PathError naming `what` and stating the rule."""
    if not isinstance(value, str) or not PLAIN_NAME.fullmatch(value):
        raise PathError(f"{what} {value!r} is not a plain name: it is used in folder names, so it must be "
                        f"{PLAIN_NAME_RULE}. Rename it (a folder elsewhere can be linked into place).")
    return value


def confined(path: Path | str, root: Path | str, what: str) -> Path:
    """`path` if, resolved (links followed), it lies inside `root`; else a PathError naming both."""
    path, root = Path(path), Path(root)
    real, root_real = path.resolve(), root.resolve()
    if real != root_real and not real.is_relative_to(root_real):
        raise PathError(f"{what} {str(path)!r} resolves to {real}, outside {root_real}, the folder it must "
                        f"stay in. Use a plain name without '/', '..' or links leaving the folder.")
    return path
