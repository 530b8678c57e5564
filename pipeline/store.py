"""The content-addressed result store (the cache). It is the engine's only state.

Layout under the cache root:
    objects/<k[:2]>/<k>/     published results: the stage's output files + manifest.json (written last)
    tmp/<k>.<token>/         work in progress of the lease holder with <token>; published by one
                             os.rename of the whole folder
    scratch/<k>/             in-stage checkpoints and progress.json; kept across failed or killed
                             attempts, deleted after a successful publish (and by gc when stale)
    leases/<k>.lease         who is computing <k> right now, and its heartbeat file (pipeline.lease)
    quarantine/<k>.<time>/   results whose files did not match their manifest; never used again
    pins/<k>                 gc roots besides run records
    runs/<h>.json            {"run_file": path}: every run record that used this store (gc roots,
                             wherever the run folder lives; dropped once the run file is deleted)
    config.json              {"salt": ...}: store-wide salt entering every key
    hashmemo.json            memo of input-file hashes (pipeline.hashing)
A result is only ever used after its files were checked against its manifest (sizes, and sha256
unless a caller asks for the cheap check).
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.errors import UserError
from pipeline.hashing import ContentHasher, file_records, list_files, record_problems, write_json_atomic
from pipeline.keys import FORMAT_VERSION
from pipeline.lease import Lease, LeaseWatch, beat_path, read_lease

MANIFEST = "manifest.json"
log = logging.getLogger("pipeline.store")


class StoreError(UserError):
    pass


def folder_size(path: Path) -> int:
    total = 0
    for folder, _, files in os.walk(path):
        for name in files:
            try:
                total += (Path(folder) / name).lstat().st_size
            except OSError:
                pass
    return total


def _write_manifest(folder: Path, manifest: dict[str, Any]) -> None:
    write_json_atomic(folder / MANIFEST, manifest)


@dataclass
class GcReport:
    removed: list[str] = field(default_factory=list)
    kept: int = 0
    freed_bytes: int = 0
    removed_other: list[str] = field(default_factory=list)   # tmp, scratch, quarantine folders


class Store:
    def __init__(self, root: Path | str, lease_ttl_s: float = 30.0):
        self.root = Path(root).absolute()
        self.objects = self.root / "objects"
        self.tmp = self.root / "tmp"
        self.scratch = self.root / "scratch"
        self.leases = self.root / "leases"
        self.quarantine_dir = self.root / "quarantine"
        self.pins = self.root / "pins"
        self.lease_ttl_s = lease_ttl_s
        self.hasher = ContentHasher(self.root / "hashmemo.json")

    # ---- configuration -------------------------------------------------------------------------
    @property
    def salt(self) -> str:
        path = self.root / "config.json"
        if not path.exists():
            return ""
        try:
            return str(json.loads(path.read_text(encoding="utf-8")).get("salt", ""))
        except ValueError as exc:
            raise StoreError(f"{path}: not valid JSON ({exc}); fix or delete it (it only holds the salt).")

    def set_salt(self, salt: str) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        write_json_atomic(self.root / "config.json", {"salt": salt})

    # ---- paths ---------------------------------------------------------------------------------
    def object_path(self, key: str) -> Path:
        return self.objects / key[:2] / key

    def scratch_path(self, key: str) -> Path:
        return self.scratch / key

    def lease(self, key: str) -> Lease:
        return Lease(self.leases / f"{key}.lease", ttl_s=self.lease_ttl_s)

    def lease_holder(self, key: str):
        return read_lease(self.leases / f"{key}.lease")

    def new_tmp(self, key: str, token: str | None = None) -> Path:
        """tmp/<key>.<token>: a lease holder's work in progress, named by its lease token so that nobody
        mistakes a live writer's folder for an orphan (without a token: a random name, for tests)."""
        path = self.tmp / f"{key}.{token or uuid.uuid4().hex[:12]}"
        path.mkdir(parents=True)
        return path

    # ---- orphaned work in progress --------------------------------------------------------------
    def orphan_tmp(self, key: str | None = None, expired: frozenset[str] = frozenset()) -> list[Path]:
        """tmp/<key>.<token> folders that no live writer owns: nobody holds a lease on <key>, or its holder
        is provably dead (a dead process on this host), or the lease belongs to another token (the folder's
        writer lost its lease, so it will never publish it). `expired`: keys whose leases an observer saw
        expire (gc). No clock is read: a writer creates its folder only while holding the lease, under its
        token, and removes or publishes it before release, so a live writer's folder is never listed,
        whatever the clocks of the hosts sharing the cache say."""
        if not self.tmp.is_dir():
            return []
        found = []
        for path in sorted(self.tmp.iterdir()):
            folder_key, _, tag = path.name.partition(".")
            if key is not None and folder_key != key:
                continue
            holder = self.lease_holder(folder_key)
            if holder is None or holder.dead_here() or holder.token != tag or folder_key in expired:
                found.append(path)
        return found

    def remove_orphan_tmp(self, key: str | None = None) -> list[str]:
        """Delete the folders `orphan_tmp` lists; returns their names (tmp/<key>.<token>)."""
        removed = []
        for path in self.orphan_tmp(key):
            shutil.rmtree(path, ignore_errors=True) if path.is_dir() else path.unlink(missing_ok=True)
            removed.append(f"{self.tmp.name}/{path.name}")
        if removed:
            log.info("removed %d temporary folder(s) left by killed writers: %s", len(removed), ", ".join(removed))
        return removed

    def watch_leases(self, seconds: float | None = None, poll_s: float = 0.5) -> tuple[set[str], set[str]]:
        """(expired, live) keys among the current leases, judged the observer's way: a holder that is dead
        here is expired at once; the others are watched for up to `seconds` (default: the longest holder
        ttl) on this process's monotonic clock, and those whose heartbeat did not change are expired."""
        expired, watched = set(), {}
        for path in sorted(self.leases.glob("*.lease")) if self.leases.is_dir() else []:
            holder = read_lease(path)
            if holder is None:
                continue
            key = path.name.removesuffix(".lease")
            if holder.dead_here():
                expired.add(key)
            else:
                watched[key] = (path, holder)
        if watched:
            watch = LeaseWatch(default_ttl_s=self.lease_ttl_s)
            ttl = max(h.ttl_s or self.lease_ttl_s for _, h in watched.values())
            deadline = watch.clock() + (ttl if seconds is None else seconds) + poll_s
            while watched and watch.clock() < deadline:
                for key, (path, holder) in list(watched.items()):
                    if read_lease(path) != holder:          # released or taken over meanwhile: not expired
                        del watched[key]
                    elif watch.expired(path, holder):
                        expired.add(key)
                        del watched[key]
                if watched:
                    time.sleep(poll_s)
        return expired, set(watched)

    # ---- reading -------------------------------------------------------------------------------
    def has(self, key: str) -> bool:
        """Published (manifest present); no file checks. For listings, not for use."""
        return (self.object_path(key) / MANIFEST).is_file()

    def manifest(self, key: str) -> dict[str, Any] | None:
        try:
            return json.loads((self.object_path(key) / MANIFEST).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None

    def problems(self, key: str, full: bool = True) -> list[str]:
        """What is wrong with a published entry: missing/extra/resized/changed files. [] if intact."""
        folder = self.object_path(key)
        manifest = self.manifest(key)
        if manifest is None:
            return [f"{folder / MANIFEST}: missing or not valid JSON"]
        if manifest.get("key") != key or manifest.get("format") != FORMAT_VERSION:
            what = f"key {manifest.get('key')!r}, format {manifest.get('format')!r}"
            return [f"{folder / MANIFEST}: describes {what}"]
        return record_problems(folder, manifest.get("files", {}), list_files(folder, frozenset({MANIFEST})),
                               full=full, name=lambda rel: str(folder / rel), unrecorded="not listed in the manifest")

    def lookup(self, key: str, full: bool = True) -> Path | None:
        """The published folder for `key` if present and intact; a damaged entry is reported,
        quarantined and treated as absent (so it gets recomputed)."""
        folder = self.object_path(key)
        if not folder.exists():
            return None
        found = self.problems(key, full=full)
        if not found:
            return folder
        log.warning("cache entry %s is damaged and will be recomputed: %s", key[:12], "; ".join(found))
        self.quarantine(key, found)
        return None

    def entries(self) -> Iterator[tuple[str, Path]]:
        if not self.objects.is_dir():
            return
        for prefix in sorted(self.objects.iterdir()):
            if prefix.is_dir():
                for folder in sorted(prefix.iterdir()):
                    yield folder.name, folder

    # ---- writing -------------------------------------------------------------------------------
    def publish(self, key: str, tmp: Path, manifest: dict[str, Any], fence: Callable[[], None] | None = None) -> Path:
        """Hash the outputs in `tmp`, write the manifest last, and rename the folder into place. `fence` is
        called right before the rename; it raises (pipeline.lease.LeaseLost) if the writer lost its lease."""
        if (tmp / MANIFEST).exists():
            raise StoreError(f"the stage wrote '{MANIFEST}' into its output folder; that name is "
                             f"reserved for the store. Rename the output file.")
        files = file_records(tmp, list_files(tmp))
        manifest = dict(manifest, key=key, format=FORMAT_VERSION, files=files)
        _write_manifest(tmp, manifest)
        final = self.object_path(key)
        final.parent.mkdir(parents=True, exist_ok=True)
        if fence is not None:
            fence()
        for _ in range(2):
            try:
                self._rename_into_place(tmp, final)
                return final
            except OSError:
                # Someone published the same key first (the rename target exists). Keep theirs if intact.
                if self.lookup(key) is not None:
                    shutil.rmtree(tmp, ignore_errors=True)
                    return final
        raise StoreError(f"could not publish {key} to {final}")

    @staticmethod
    def _rename_into_place(tmp: Path, final: Path) -> None:
        os.rename(tmp, final)

    def quarantine(self, key: str, reasons: list[str]) -> Path | None:
        self.quarantine_dir.mkdir(parents=True, exist_ok=True)
        target = self.quarantine_dir / f"{key}.{time.strftime('%Y%m%dT%H%M%S')}.{uuid.uuid4().hex[:6]}"
        try:
            os.rename(self.object_path(key), target)
        except FileNotFoundError:
            return None      # another process quarantined it first
        (target.parent / f"{target.name}.reason.txt").write_text("\n".join(reasons) + "\n", encoding="utf-8")
        return target

    def remove_scratch(self, key: str) -> None:
        shutil.rmtree(self.scratch_path(key), ignore_errors=True)

    # ---- gc roots: run records and pins --------------------------------------------------------
    def register_run(self, run_file: Path) -> None:
        run_file = Path(run_file).absolute()
        name = hashlib.sha256(str(run_file).encode("utf-8")).hexdigest()[:20]
        (self.root / "runs").mkdir(parents=True, exist_ok=True)
        write_json_atomic(self.root / "runs" / f"{name}.json", {"run_file": str(run_file)})

    def registered_run_files(self) -> list[Path]:
        """Run records that used this store and still exist (registrations of deleted ones are dropped)."""
        found = []
        folder = self.root / "runs"
        for path in sorted(folder.glob("*.json")) if folder.is_dir() else []:
            try:
                run_file = Path(json.loads(path.read_text(encoding="utf-8"))["run_file"])
            except (OSError, ValueError, KeyError):
                continue
            if run_file.exists():
                found.append(run_file)
            else:
                path.unlink(missing_ok=True)
        return found

    def pin(self, key: str) -> None:
        if not self.has(key):
            raise StoreError(f"no published cache entry {key} in {self.root}; `dualnerf cache ls` lists them.")
        self.pins.mkdir(parents=True, exist_ok=True)
        (self.pins / key).write_text("", encoding="utf-8")

    def unpin(self, key: str) -> None:
        (self.pins / key).unlink(missing_ok=True)

    def pinned(self) -> set[str]:
        return {p.name for p in self.pins.iterdir()} if self.pins.is_dir() else set()

    def resolve_prefix(self, prefix: str) -> str:
        matches = [k for k, _ in self.entries() if k.startswith(prefix)]
        if len(matches) != 1:
            raise StoreError(f"key prefix '{prefix}' matches {len(matches)} cache entries in {self.root}; "
                             f"give more characters (`dualnerf cache ls` shows keys).")
        return matches[0]

    def closure(self, roots: set[str]) -> set[str]:
        """Roots plus every upstream key their manifests name (what a root's result was built from)."""
        reached, todo = set(), list(roots)
        while todo:
            key = todo.pop()
            if key in reached:
                continue
            reached.add(key)
            manifest = self.manifest(key) or {}
            todo.extend(manifest.get("key_inputs", {}).get("upstream", {}).values())
        return reached

    def gc(self, roots: set[str], *, stale_after_s: float = 7 * 86400, dry_run: bool = False,
           watch_s: float | None = None) -> GcReport:
        """Remove published entries not reachable from `roots` + pins; tmp folders no live writer owns;
        scratch folders with no live lease that are older than `stale_after_s` (scratch of published keys
        always); leases of dead or silent holders; the quarantine. Leases whose holders are not provably
        dead are watched first (up to their ttl, `watch_s` to override) to tell live writers from dead ones."""
        report = GcReport()
        keep = self.closure(set(roots) | self.pinned())
        now = time.time()
        expired, _ = self.watch_leases(watch_s)

        def remove(path: Path, bucket: list[str], name: str) -> None:
            report.freed_bytes += folder_size(path) if path.is_dir() else path.stat().st_size
            bucket.append(name)
            if not dry_run:
                shutil.rmtree(path) if path.is_dir() else path.unlink()

        for key, folder in list(self.entries()):
            if key in keep:
                report.kept += 1
            else:
                remove(folder, report.removed, key)
        for path in self.orphan_tmp(expired=frozenset(expired)):
            remove(path, report.removed_other, f"{self.tmp.name}/{path.name}")
        if self.scratch.is_dir():
            for path in self.scratch.iterdir():
                key = path.name
                holder = self.lease_holder(key)
                if holder is not None and key not in expired:
                    continue
                if self.has(key) or now - path.stat().st_mtime > stale_after_s:
                    remove(path, report.removed_other, f"{self.scratch.name}/{path.name}")
        if self.leases.is_dir():
            for key in sorted(expired):
                path = self.leases / f"{key}.lease"
                holder = read_lease(path)
                if holder is None:
                    continue
                remove(path, report.removed_other, f"leases/{path.name}")
                beat = beat_path(path, holder.token)
                if beat.exists():
                    remove(beat, report.removed_other, f"leases/{beat.name}")
        if self.quarantine_dir.is_dir():
            for path in self.quarantine_dir.iterdir():
                remove(path, report.removed_other, f"quarantine/{path.name}")
        return report
