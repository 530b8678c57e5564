"""Names and paths that come from data files stay inside their folder.

A scene folder's files (transforms.json, a COLMAP model, scene.toml) name images, masks, point clouds
and edit ids. Resolved with links followed, every file they name must lie inside the scene folder, so
a crafted file can neither make a run read elsewhere (`../../etc/hostname`, an absolute path, a link
out of the folder) nor write elsewhere (an edit id or image name of `../x` becomes a folder name).
"""
from __future__ import annotations

import re
from pathlib import Path

PLAIN_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")
PLAIN_NAME_RULE = ("1 to 100 characters from letters, digits, '.', '_' and '-', starting with a letter or "
                   "digit (no '/', '..', spaces)")


def confine(path: Path | str, root: Path | str, *, error: type[Exception], where: str, field: str,
            value: object) -> Path:
    """`path` resolved (links followed); raises `error` naming the file, field and value when it
    lies outside `root`."""
    root_real = Path(root).resolve()
    real = Path(path).resolve()
    if real != root_real and not real.is_relative_to(root_real):
        raise error(f"{where}: {field} {str(value)!r} names {real}, which is outside the scene folder "
                    f"{root_real}. Every file a scene names must lie inside its folder (no absolute paths, "
                    f"no '..' leaving it, no links pointing out of it); copy the file into the folder and "
                    f"name it relative to it.")
    return real


def check_plain_name(value: object, *, error: type[Exception], where: str, field: str) -> str:
    """`value` if it is a plain name (see PLAIN_NAME_RULE), else raises `error` stating the rule."""
    if not isinstance(value, str) or not PLAIN_NAME.fullmatch(value):
        raise error(f"{where}: {field} {value!r} is not a plain name; it is used as a folder name, so it "
                    f"must be {PLAIN_NAME_RULE}. Rename it.")
    return value


def check_file_name(value: object, *, error: type[Exception], where: str, field: str) -> str:
    """`value` if it is a single path component (an image file name), else raises `error`."""
    if (not isinstance(value, str) or not value or value in (".", "..") or "/" in value or "\\" in value
            or "\x00" in value):
        raise error(f"{where}: {field} {value!r} is not a file name; views are identified by a file name "
                    f"without folders (no '/', '\\', '.' or '..'). Rename the file.")
    return value
