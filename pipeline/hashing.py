"""Content hashes of user files and folders, memoised on disk by (path, size, mtime_ns).

The memo makes re-keying a workflow over a 100-image folder cost one `stat` per file. A file whose
mtime is within `RACY_WINDOW_NS` of the moment it was hashed is not memoised: it could still be
rewritten within the file system's timestamp granularity without its (size, mtime) changing.
"""
from __future__ import annotations

import hashlib
import json
import os
import time
import uuid
from pathlib import Path

from pipeline.errors import UserError

RACY_WINDOW_NS = 2_000_000_000
_CHUNK = 1 << 20


class InputMissingError(UserError):
    pass


def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def list_files(folder: Path, exclude: frozenset[str] = frozenset()) -> list[str]:
    """Every file below `folder` as a sorted relative posix path, without the top-level names in `exclude`."""
    out = []
    for parent, dirnames, filenames in os.walk(folder):
        dirnames.sort()
        for name in filenames:
            rel = (Path(parent) / name).relative_to(folder).as_posix()
            if rel not in exclude:
                out.append(rel)
    return sorted(out)


def file_records(folder: Path, rels: list[str]) -> dict[str, dict]:
    """{rel: {"size", "sha256"}}: what a manifest or checksum file records of each file."""
    return {rel: {"size": (folder / rel).stat().st_size, "sha256": sha256_file(folder / rel)} for rel in rels}


def record_problems(folder: Path, expected: dict[str, dict], present: list[str], *, full: bool = True,
                    name=lambda rel: rel, unrecorded: str = "not recorded") -> list[str]:
    """What is wrong with `folder` against its `file_records`: one "name(rel): what" line for each
    missing, resized, changed (sha256, only when `full`) or unrecorded (`present` but not expected) file."""
    found = []
    for rel, meta in sorted(expected.items()):
        try:
            size = (folder / rel).stat().st_size
        except OSError:
            found.append(f"{name(rel)}: missing")
            continue
        if size != meta["size"]:
            found.append(f"{name(rel)}: size {size}, {meta['size']} when recorded (truncated or overwritten)")
        elif full and sha256_file(folder / rel) != meta["sha256"]:
            found.append(f"{name(rel)}: content changed (sha256 differs from the record)")
    found += [f"{name(rel)}: {unrecorded}" for rel in present if rel not in expected]
    return found


def write_json_atomic(path: Path, data: object, indent: int | None = 1) -> None:
    """Write JSON to a unique temp name in the same folder, then os.replace: readers see old or new.
    indent=None is ~10x faster (the C encoder only handles one-shot, unindented output)."""
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    tmp.write_text(json.dumps(data, indent=indent, sort_keys=True) + "\n", encoding="utf-8")
    os.replace(tmp, path)


class ContentHasher:
    """Hashes files and folders; `save()` persists the memo (lost concurrent updates only cost re-hashing)."""

    def __init__(self, memo_path: Path | None):
        self.memo_path = memo_path
        self._memo: dict[str, list] | None = None
        self._dirty = False

    def _load(self) -> dict[str, list]:
        if self._memo is None:
            self._memo = {}
            if self.memo_path is not None and self.memo_path.exists():
                try:
                    self._memo = json.loads(self.memo_path.read_text(encoding="utf-8"))
                except (OSError, ValueError):
                    self._memo = {}   # a damaged memo is only a cache: start over
        return self._memo

    def file_sha256(self, path: Path, stat: os.stat_result | None = None) -> str:
        memo = self._load()
        st = stat or path.stat()
        name = str(path.absolute())
        hit = memo.get(name)
        if hit is not None and hit[0] == st.st_size and hit[1] == st.st_mtime_ns:
            return hit[2]
        sha = sha256_file(path)
        if time.time_ns() - st.st_mtime_ns > RACY_WINDOW_NS:
            memo[name] = [st.st_size, st.st_mtime_ns, sha]
            self._dirty = True
        return sha

    def hash_path(self, path: Path, what: str = "input") -> str:
        """'file:<sha256>' of a file's bytes or 'dir:<sha256>' over the sorted (relative path, size,
        sha256) of every file below a folder, links to files and folders followed."""
        path = Path(path)
        if path.is_file():
            return "file:" + self.file_sha256(path)
        if not path.is_dir():
            raise InputMissingError(
                f"{what}: '{path}' does not exist (or is neither a file nor a folder). Check the path in "
                f"the workflow file; relative paths are resolved against the current directory."
            )
        listing: list[list] = []
        self._list_folder(path, "", frozenset({os.path.realpath(path)}), listing)
        listing.sort()
        blob = json.dumps(listing, separators=(",", ":")).encode("utf-8")
        return "dir:" + hashlib.sha256(blob).hexdigest()

    def _list_folder(self, folder: Path, prefix: str, chain: frozenset[str], listing: list[list]) -> None:
        """Append [relative path, size, sha256] of every file below `folder`. Links are followed (what is
        read through a link is part of the input); a link to a folder above itself is not (a cycle)."""
        for entry in sorted(os.scandir(folder), key=lambda e: e.name):
            rel = prefix + entry.name
            if entry.is_dir():
                real = os.path.realpath(entry.path)
                if real not in chain:
                    self._list_folder(Path(entry.path), rel + "/", chain | {real}, listing)
            elif entry.is_file():
                st = os.stat(entry.path)
                listing.append([rel, st.st_size, self.file_sha256(Path(entry.path), st)])

    def save(self) -> None:
        if self._dirty and self.memo_path is not None:
            self.memo_path.parent.mkdir(parents=True, exist_ok=True)
            write_json_atomic(self.memo_path, self._memo, indent=None)
            self._dirty = False
