"""Error messages and documentation name only command-line flags and stage parameters that exist.

Every `--flag` and `<stage>.<param>` in the strings of `raise` statements (read from the source with ast,
f-string parts included) and in README.md and docs/*.md must be an option of some `dualnerf` parser or a
field of that stage's Params; the docs may also name the options of the benchmark scripts. Flags of other tools that the docs quote (pip, pytest, git, make) are listed
in OTHER_TOOLS_FLAGS.
"""
import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ("dualnerf", "pipeline", "stages", "experiments")
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
# Flags of other programs that the docs show in full commands.
OTHER_TOOLS_FLAGS = {"--no-deps", "--no-compile", "--upgrade", "--force-reinstall", "--help", "--version", "--collect-only",
                     # ray start / ray status (docs/cluster.md and the cluster probe's messages)
                     "--head", "--address", "--port", "--num-cpus", "--num-gpus", "--block", "--temp-dir",
                     # pytest-xdist's scheduler (the Makefile's test command) and py-spy (docs/benchmarks.md)
                     "--dist", "--native"}
FILE_SUFFIXES = {"json", "jsonl", "py", "toml", "png", "mp4", "md", "h", "cpp", "pt", "log", "csv", "txt", "cff"}
FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*[a-z0-9]")


def _stage_params() -> dict[str, set[str]]:
    from experiments.params import parameters, stage_names

    return {stage: {p.name for p in parameters(stage)} for stage in stage_names()}


STAGE_PARAMS = _stage_params()
PARAM = re.compile(r"(?<![\w./-])(" + "|".join(STAGE_PARAMS) + r")\.([A-Za-z_]\w*)")


def _parser_flags() -> set[str]:
    from experiments.cli import _command_parsers, build_parser

    parser = build_parser()
    return {option for p in [parser, *_command_parsers(parser)] for action in p._actions
            for option in action.option_strings if option.startswith("--")}


def _benchmark_flags() -> set[str]:
    """The options of the benchmark scripts (`python -m benchmarks.<name> --flag`), read with ast."""
    flags = set()
    for path in sorted((ROOT / "benchmarks").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "add_argument":
                flags |= {arg.value for arg in node.args
                          if isinstance(arg, ast.Constant) and str(arg.value).startswith("--")}
    return flags


def _error_strings() -> list[tuple[str, str]]:
    """(where, text) of every string constant inside a `raise` statement of the product's source."""
    found = []
    for package in SOURCE:
        for path in sorted((ROOT / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Raise) and node.exc is not None:
                    for sub in ast.walk(node.exc):
                        if isinstance(sub, ast.Constant) and isinstance(sub.value, str):
                            found.append((f"{path.relative_to(ROOT)}:{node.lineno}", sub.value))
    return found


def _doc_strings() -> list[tuple[str, str]]:
    return [(f"{path.relative_to(ROOT)}:{n}", line) for path in DOCS
            for n, line in enumerate(path.read_text().splitlines(), start=1)]


def _bad(texts, flags) -> list[str]:
    bad = []
    for where, text in texts:
        bad += [f"{where}: {flag}" for flag in FLAG.findall(text) if flag not in flags | OTHER_TOOLS_FLAGS]
        for stage, name in PARAM.findall(text):
            if name not in STAGE_PARAMS[stage] and name not in FILE_SUFFIXES:
                bad.append(f"{where}: {stage}.{name}")
    return bad


def test_the_checks_find_what_they_look_for():
    flags = _parser_flags()
    assert {"--cache", "--set", "--force", "--dry-run", "--out", "--markdown"} <= flags
    assert _bad([("x", "use --encoder-model or edit.encoder_models, not edit.json")], flags) == \
        ["x: --encoder-model", "x: edit.encoder_models"]
    assert len(_error_strings()) > 200
    assert {"--iterations", "--nodes", "--cores"} <= _benchmark_flags()


@pytest.mark.parametrize("what", ["error messages", "docs"])
def test_only_existing_flags_and_parameters_are_named(what):
    texts = _error_strings() if what == "error messages" else _doc_strings()
    flags = _parser_flags() if what == "error messages" else _parser_flags() | _benchmark_flags()
    assert _bad(texts, flags) == []
