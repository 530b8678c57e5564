"""The CLI framework (exit codes, lazy imports, missing command modules) and `status`."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import types
from pathlib import Path

import pytest

from experiments import cli
from experiments.commands.status import print_status
from pipeline.dag import Step, compute_keys
from pipeline.errors import UserError
from pipeline.executors import SerialExecutor
from pipeline.runner import run_steps
from pipeline.status import workflow_status
from pipeline.store import Store
from tests.pipeline_stages import REGISTRY

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "ray", "numpy", "tqdm", "diffusers", "transformers", "cv2", "onnxruntime", "pycolmap")


def test_help_lists_commands_without_heavy_imports():
    probe = ("import sys, experiments.cli as c\n"
             "text = c.build_parser().format_help()\n"
             f"print(text); print('HEAVY', sorted(m for m in {HEAVY!r} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", probe], check=False, capture_output=True, text=True, cwd=ROOT,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert out.returncode == 0, out.stderr
    assert "cache" in out.stdout and "status" in out.stdout
    assert out.stdout.strip().endswith("HEAVY []")


def fake_command(monkeypatch, name: str, handler) -> None:
    module = types.ModuleType(f"experiments.commands.{name}")

    def register(subparsers):
        subparsers.add_parser(name).set_defaults(handler=handler)

    module.register = register
    monkeypatch.setitem(sys.modules, module.__name__, module)
    monkeypatch.setattr(cli, "COMMANDS", ["cache", "not_written_yet", name])


def test_exit_codes_user_internal_interrupt(monkeypatch, capsys):
    class StageInputError(ValueError):
        user_error = True          # the rule for library code that cannot import pipeline.errors

    fake_command(monkeypatch, "user", lambda args: (_ for _ in ()).throw(UserError("fix the file x.toml")))
    assert cli.main(["user"]) == 2
    assert capsys.readouterr().err.strip() == "dualnerf: error: fix the file x.toml"
    fake_command(monkeypatch, "lib", lambda args: (_ for _ in ()).throw(StageInputError("image 3 is empty")))
    assert cli.main(["lib"]) == 2
    fake_command(monkeypatch, "plain", lambda args: (_ for _ in ()).throw(ValueError("a bug")))
    with pytest.raises(ValueError, match="a bug"):       # not a user error: traceback, exit 1
        cli.main(["plain"])
    fake_command(monkeypatch, "ctrlc", lambda args: (_ for _ in ()).throw(KeyboardInterrupt()))
    assert cli.main(["ctrlc"]) == 130


def test_only_the_missing_command_module_itself_is_skipped(monkeypatch):
    real_import = cli.importlib.import_module

    def import_module(name):
        if name == "experiments.commands.status":
            raise ModuleNotFoundError("No module named 'yaml'", name="yaml")   # a broken command module
        return real_import(name)

    monkeypatch.setattr(cli.importlib, "import_module", import_module)
    with pytest.raises(ModuleNotFoundError, match="yaml"):
        cli.build_parser()


def test_cli_user_error_has_no_traceback_and_cache_env(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT), DUALNERF_CACHE=str(tmp_path / "envcache"))
    out = subprocess.run([sys.executable, "-m", "experiments.cli", "cache", "pin", "abc"], check=False, capture_output=True,
                         text=True, env=env, cwd=tmp_path)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "abc" in out.stderr and str(tmp_path / "envcache") in out.stderr


def test_bad_workflow_toml_names_file_and_line(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[workflow]\nname = "x"\nseeds = [0, 1]]\nedit = "snow"\n')
    out = subprocess.run([sys.executable, "-m", "experiments.cli", "--cache", str(tmp_path / "c"), "status", str(bad)],
                         check=False, capture_output=True, text=True, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert str(bad) in out.stderr and "line 3" in out.stderr


def test_status_reports_each_state(tmp_path, capsys):
    store, runs = Store(tmp_path / "cache"), tmp_path / "runs"
    done = Step("count", {"n": 2}, label="done")
    failed = Step("fail", {"message": "bad mask"}, {"left": done}, label="failed")
    running = Step("count", {"n": 50}, label="running")
    partial = Step("count", {"n": 60}, label="partial")
    pending = Step("add", {}, {"left": partial}, label="pending")
    run_steps([done, failed], registry=REGISTRY, store=store, executor=SerialExecutor(threads=1),
              run_dir=runs / "r1", quiet=True)
    keys = {s.label: k.key for s, k in compute_keys([running, partial], registry=REGISTRY, store=store).items()}
    lease = store.lease(keys["running"])
    assert lease.try_acquire()
    try:
        (store.scratch_path(keys["running"])).mkdir(parents=True)
        (store.scratch_path(keys["running"]) / "progress.json").write_text(json.dumps(
            {"desc": "fitting", "done": 12, "total": 50, "eta_s": 30.0, "updated": 1e12}))
        (store.scratch_path(keys["partial"]) / "checkpoints" / "000000000007").mkdir(parents=True)
        rows = workflow_status([failed, running, pending], registry=REGISTRY, store=store, runs_dir=runs)
    finally:
        lease.release()
    states = {r.label: (r.state, r.detail) for r in rows}
    assert {label: s for label, (s, _) in states.items()} == {
        "done": "done", "failed": "failed", "running": "running", "partial": "partial", "pending": "pending"}
    assert "BadInputError: bad mask" in states["failed"][1] and "failed.log" in states["failed"][1]
    assert "fitting 12/50, eta 30s" in states["running"][1] and f"pid {os.getpid()}" in states["running"][1]
    print_status(rows)
    printed = capsys.readouterr().out
    assert "1 done, 1 failed, 1 partial, 1 pending, 1 running" in printed
