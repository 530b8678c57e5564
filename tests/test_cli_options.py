"""The command line's options: global options after the command too, one output-folder flag (--out, the
older --reports hidden), --version, one way to list scenes, `run --force STAGE`, `params [STAGE]`."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

from experiments import cli

ROOT = Path(__file__).resolve().parents[1]
SMOKE = str(ROOT / "workflows" / "smoke.toml")


@pytest.mark.parametrize("argv", [
    ["--cache", "c", "--runs", "r", "--quiet", "run", SMOKE],
    ["run", SMOKE, "--cache", "c", "--runs", "r", "--quiet"],
    ["--cache", "x", "run", SMOKE, "--cache", "c", "--runs", "r", "--quiet"],      # the later one wins
])
def test_global_options_before_or_after_the_command(argv):
    args = cli.build_parser().parse_args(argv)
    assert (args.cache, args.runs, args.quiet) == (Path("c"), Path("r"), True)


def test_global_options_keep_their_defaults_and_reach_nested_actions():
    args = cli.build_parser().parse_args(["run", SMOKE])
    assert (args.cache, args.runs, args.quiet) == (None, Path("runs"), False)
    args = cli.build_parser().parse_args(["cache", "ls", "--cache", "c"])
    assert args.cache == Path("c")
    args = cli.build_parser().parse_args(["status", SMOKE, "--runs", "elsewhere"])
    assert args.runs == Path("elsewhere")


def test_one_output_folder_flag_with_the_older_one_hidden():
    parser = cli.build_parser()
    assert parser.parse_args(["run", SMOKE, "--out", "d"]).out == Path("d")
    assert parser.parse_args(["run", SMOKE, "--reports", "d"]).out == Path("d")
    assert parser.parse_args(["report", SMOKE, "--out", "d"]).out == Path("d")
    assert parser.parse_args(["scene", "tiny", "--out", "d"]).out == Path("d")
    run_help = next(p for p in cli._command_parsers(parser) if p.prog.endswith(" run")).format_help()
    assert "--out DIR" in run_help and "--reports" not in run_help


def test_version_and_one_way_to_list_scenes(capsys):
    with pytest.raises(SystemExit) as exit_:
        cli.main(["--version"])
    assert exit_.value.code == 0 and capsys.readouterr().out.startswith("dualnerf ")
    assert cli.main(["scene", "list"]) == 0
    listed = capsys.readouterr().out
    assert "campsite" in listed and "snow" in listed
    scene_help = next(p for p in cli._command_parsers(cli.build_parser()) if p.prog.endswith(" scene"))
    assert "--list" not in scene_help.format_help()        # the older spelling still works, unlisted
    assert cli.main(["scene", "--list"]) == 0 and capsys.readouterr().out == listed


def test_params_prints_a_stages_parameters(capsys):
    assert cli.main(["params", "edit"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("edit (stage version ")
    assert "  edit.dual_field = true   (bool; set by the workflow from methods)" in out
    assert "  edit.num_threads = 0   (int; not in the key)" in out
    assert "  edit.editor_model = \"\"   (str)" in out and "hub id" in out
    assert cli.main(["params", "editt"]) == 2
    assert "unknown stage 'editt'; the stages are scene, preprocess, fit, edit" in capsys.readouterr().err
    assert cli.main(["params"]) == 0
    everything = "\n" + capsys.readouterr().out
    assert all(f"\n{stage} (stage version" in everything
               for stage in ("scene", "preprocess", "fit", "edit", "gtviews", "perframe", "evaluate"))


def test_params_comments_span_lines_and_comments_above():
    from experiments.params import parameters

    edit = {p.name: p for p in parameters("edit")}
    assert edit["lpips_weight"].comment.endswith("0 at the CPU preset's 1024 rays (module docstring)")
    assert edit["checkpoint_every_rounds"].comment.startswith("Non-semantic (resume is exact from any round)")
    assert not edit["checkpoint_every_rounds"].in_key and edit["iterations"].in_key


def test_force_recomputes_the_stage_and_what_is_downstream(tmp_path, monkeypatch, capsys):
    from tests.test_workflow_grid import FAKES, RUNS_LOG

    monkeypatch.setattr("stages.STAGES", FAKES)
    log = tmp_path / "computed.jsonl"
    monkeypatch.setenv(RUNS_LOG, str(log))
    sweep = str(ROOT / "workflows" / "sweep_blend.toml")
    argv = ["run", sweep, "--executor", "serial", "--no-report", "--cache", str(tmp_path / "c"), "--runs",
            str(tmp_path / "r"), "--quiet", "--set", "scenes_dir=/nonexistent", "--set", "methods=[\"DualNeRF\"]",
            "--set", "exclude=[]", "--set", "w_max=[0.1]", "--set", "lambda=[0.005]"]

    def computed(*extra):
        log.write_text("")
        assert cli.main([*argv, *extra]) == 0
        return sorted(json.loads(line)["stage"] for line in log.read_text().splitlines())

    assert computed() == ["edit", "evaluate", "evaluate", "fit", "preprocess", "scene"]
    assert computed() == []
    capsys.readouterr()
    assert cli.main([*argv, "--force", "edit", "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert out.count("cached, forced: recomputed") == 2 and out.count("  cached\n") == 4
    assert computed("--force", "edit") == ["edit", "evaluate"]      # not the unedited row's evaluation
    assert "moved to" in capsys.readouterr().out
    assert len(list((tmp_path / "c" / "quarantine").glob("*.reason.txt"))) == 2
    assert computed("--force", "fit,scene") == ["edit", "evaluate", "evaluate", "fit", "preprocess", "scene"]
    assert cli.main([*argv, "--force", "fitt"]) == 2
    assert "fitt names no stage of this workflow; its stages are scene" in capsys.readouterr().err


def test_the_installed_entry_point_is_the_experiments_cli():
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["scripts"]["dualnerf"] == "experiments.cli:main"
    out = subprocess.run([sys.executable, "-m", "experiments.cli", "--version"], capture_output=True, text=True,
                         cwd=ROOT, check=False)
    assert out.returncode == 0 and out.stdout.startswith("dualnerf ")
