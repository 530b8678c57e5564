"""`dualnerf cache ls | verify | gc | pin | unpin | salt`: inspect and maintain the result store."""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def register(subparsers) -> None:
    parser = subparsers.add_parser("cache", help="inspect and maintain the result store",
                                   description="Inspect and maintain the content-addressed result store.")
    sub = parser.add_subparsers(dest="cache_command", metavar="ACTION", required=True)
    ls = sub.add_parser("ls", help="list entries: key, stage, label, params summary, size, age")
    ls.add_argument("--stage", help="only entries of this stage")
    ls.set_defaults(handler=_ls)
    verify = sub.add_parser("verify", help="check every entry's files against its manifest, or recompute entries "
                                           "and compare their bytes (--recompute)")
    verify.add_argument("--quarantine", action="store_true", help="move damaged entries to quarantine/")
    verify.add_argument("--recompute", metavar="KEY|STAGE",
                        help="compute this entry (a key or unique prefix; or a stage name: its newest entries) "
                             "again from scratch in a scratch store and compare every file with the cached bytes")
    verify.add_argument("--limit", type=int, default=1, help="with a stage name: how many entries (default 1)")
    verify.add_argument("--threads", type=int, default=0,
                        help="threads for the recomputation (default: all cores; results must not depend on it)")
    verify.add_argument("--scratch", type=Path, default=None,
                        help="scratch store folder (default: a temporary folder, deleted afterwards)")
    verify.set_defaults(handler=_verify)
    gc = sub.add_parser("gc", help="remove entries no run record (under --runs) or pin reaches")
    gc.add_argument("--dry-run", action="store_true", help="only list what would be removed")
    gc.add_argument("--stale-days", type=float, default=7.0,
                    help="also remove scratch (checkpoint) folders untouched this long (default 7)")
    gc.add_argument("--force", action="store_true",
                    help="allow removing every entry when no run record or pin is found")
    gc.set_defaults(handler=_gc)
    for name, func, text in (("pin", _pin, "keep KEY (and what it was built from) through gc"),
                             ("unpin", _unpin, "remove a pin")):
        p = sub.add_parser(name, help=text)
        p.add_argument("key", help="full key or unique prefix")
        p.set_defaults(handler=func)
    salt = sub.add_parser("salt", help="show or set the store-wide salt (a new salt disowns every result)")
    salt.add_argument("value", nargs="?")
    salt.set_defaults(handler=_salt)


def _human_size(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)


def _human_age(seconds: float) -> str:
    for unit, span in (("d", 86400), ("h", 3600), ("m", 60)):
        if seconds >= span:
            return f"{seconds / span:.0f}{unit}"
    return f"{seconds:.0f}s"


def _params_summary(params: dict, limit: int = 60) -> str:
    text = ",".join(f"{k}={json.dumps(v)}" for k, v in sorted(params.items()))
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _ls(args: argparse.Namespace) -> int:
    from experiments.cli import open_store
    from pipeline.store import Store  # noqa: F401  (import-light module)

    store = open_store(args)
    pinned = store.pinned()
    now = time.time()
    rows = []
    for key, folder in store.entries():
        manifest = store.manifest(key) or {}
        stage = manifest.get("stage", "?")
        if args.stage and stage != args.stage:
            continue
        size = sum(f["size"] for f in manifest.get("files", {}).values())
        params = manifest.get("key_inputs", {}).get("params", {})
        age = _human_age(now - manifest["finished"]) if "finished" in manifest else "?"
        rows.append((key[:12] + ("*" if key in pinned else ""), stage, manifest.get("label", ""),
                     _human_size(size), age, _params_summary(params)))
    if not rows:
        print(f"no entries in {store.root}")
        return 0
    header = ("KEY", "STAGE", "LABEL", "SIZE", "AGE", "PARAMS")
    widths = [max(len(str(r[i])) for r in rows + [header]) for i in range(5)]
    for row in [header] + rows:
        print("  ".join(str(c).ljust(w) for c, w in zip(row[:5], widths)) + "  " + row[5])
    print(f"{len(rows)} entries in {store.root} (* = pinned)")
    return 0


def _verify(args: argparse.Namespace) -> int:
    from experiments.cli import open_store

    store = open_store(args)
    if args.recompute:
        return _recompute(store, args)
    bad = 0
    count = 0
    for key, _ in list(store.entries()):
        count += 1
        problems = store.problems(key, full=True)
        if problems:
            bad += 1
            for problem in problems:
                print(f"DAMAGED {key[:12]}: {problem}")
            if args.quarantine:
                print(f"  moved to {store.quarantine(key, problems)}")
    orphans = store.orphan_tmp()
    for path in orphans:
        print(f"ORPHAN {store.tmp.name}/{path.name}: left by a writer that died; removed when the next run "
              f"starts (or by `dualnerf cache gc`)")
    print(f"verified {count} entries: {count - bad} intact, {bad} damaged"
          + (f"; {len(orphans)} orphaned temporary folder(s)" if orphans else ""))
    return 1 if bad else 0


def _recompute(store, args: argparse.Namespace) -> int:
    """Recompute entries from scratch and compare bytes: 0 when every one is identical, 1 otherwise."""
    import tempfile

    from pipeline.executors import cpu_count
    from pipeline.recompute import entries_of, recompute
    from stages import STAGES
    from stages.numerics import FILE_COMPARERS

    keys = entries_of(store, args.recompute)[: max(1, args.limit)]
    threads = args.threads or cpu_count()
    differing = 0
    with tempfile.TemporaryDirectory(prefix="dualnerf-recompute-") as tmp:
        scratch = args.scratch or Path(tmp)
        for key in keys:
            label = (store.manifest(key) or {}).get("label", key[:12])
            print(f"recomputing {label} ({key[:12]}) from scratch on {threads} thread(s) ...", flush=True)
            result = recompute(store, key, STAGES, scratch, FILE_COMPARERS, threads=threads)
            if result.identical:
                print(f"IDENTICAL {key[:12]} {result.label}: every file has the cached bytes "
                      f"(recomputed in {result.seconds:.1f} s)")
            else:
                differing += 1
                print(f"DIFFERENT {key[:12]} {result.label}: {len(result.differences)} file(s) differ "
                      f"(recomputed in {result.seconds:.1f} s)")
                for line in result.differences:
                    print(f"  {line}")
    print(f"recomputed {len(keys)} entr{'y' if len(keys) == 1 else 'ies'}: {len(keys) - differing} identical, "
          f"{differing} different")
    return 1 if differing else 0


def _gc(args: argparse.Namespace) -> int:
    from experiments.cli import open_store
    from pipeline.runrecord import referenced_keys
    from pipeline.store import StoreError

    store = open_store(args)
    run_files = store.registered_run_files()
    roots = referenced_keys(args.runs, run_files)
    if not roots and not store.pinned() and not args.force and any(True for _ in store.entries()):
        raise StoreError(f"no run records found (under {args.runs} or registered in {store.root}/runs) and "
                         f"nothing is pinned, so gc would remove every entry. Check --runs, or pass --force.")
    report = store.gc(roots, stale_after_s=args.stale_days * 86400, dry_run=args.dry_run)
    verb = "would remove" if args.dry_run else "removed"
    for key in report.removed:
        print(f"{verb} {key[:12]}")
    for name in report.removed_other:
        print(f"{verb} {name}")
    print(f"{verb} {len(report.removed)} entries and {len(report.removed_other)} tmp/scratch/quarantine "
          f"folders ({_human_size(report.freed_bytes)}); kept {report.kept} reachable from "
          f"{len(roots)} keys in run records ({args.runs} and {len(run_files)} registered) "
          f"and {len(store.pinned())} pins")
    return 0


def _pin(args: argparse.Namespace) -> int:
    from experiments.cli import open_store

    store = open_store(args)
    key = store.resolve_prefix(args.key)
    store.pin(key)
    print(f"pinned {key}")
    return 0


def _unpin(args: argparse.Namespace) -> int:
    from experiments.cli import open_store

    store = open_store(args)
    pinned = [k for k in store.pinned() if k.startswith(args.key)]
    from pipeline.store import StoreError

    if len(pinned) != 1:
        raise StoreError(f"key prefix '{args.key}' matches {len(pinned)} pins; give more characters.")
    store.unpin(pinned[0])
    print(f"unpinned {pinned[0]}")
    return 0


def _salt(args: argparse.Namespace) -> int:
    from experiments.cli import open_store

    store = open_store(args)
    if args.value is None:
        print(store.salt)
    else:
        store.set_salt(args.value)
        print(f"salt set to {args.value!r}: every step will be recomputed under new keys")
    return 0
