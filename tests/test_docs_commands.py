"""Every command in the README and docs/ runs (so none can rot).

The fenced ```sh blocks of README.md and docs/**/*.md are run with bash, file by file in a fresh sandbox
folder (commands of one file in order, sharing it), with `dualnerf` on PATH as this checkout's CLI. Most
run as written. Those in REWRITES run in the cheaper form given there, for the reason given there; a
`dualnerf run` that is neither a dry run nor in REWRITES fails this test, and so does a `make` command
missing from it: a new expensive command in the docs needs a decision here. Inline `dualnerf ...` code
spans are parsed by the CLI's parser (every flag and argument must be accepted) but not run. Blocks marked
`<!-- cluster-test: NAME -->` (docs/cluster.md: `ray start`, the run on the cluster) are not run here:
tests/test_cluster.py runs them, as written, on a cluster of separate Ray nodes.
"""
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
TINY_RUN = ("--set fit.iterations=40 --set fit.eval_every=20 --set fit.checkpoint_every=20 "
            "--set fit.plane_max_resolution=128 --set evaluate.n_frames=4")

# command as written (whitespace-normalised, comments removed) -> (what runs instead, why)
REWRITES = {
    # The make targets install into .venv and run for minutes to half an hour (the ablation) or are this
    # test suite itself (make test): `make -n` prints their recipes, and the dualnerf commands in them run
    # as dry runs (the grid, every step and its key: validates the workflow, the overrides and every
    # step's parameters).
    "make ablation SCENE=campsite": ("@make ablation SCENE=campsite", "a 75-minute run"),
    "make test": ("@make test", "the test suite itself, then a 2-minute smoke run"),
    # Real model weights are not on this machine (and no network): dry runs check every parameter.
    "dualnerf run workflows/ablation.toml --set scene=campsite --set edit.editor=ip2p "
    "--set edit.editor_model=timbrooks/instruct-pix2pix --set edit.encoder=clip --set edit.encoder_model=models/clip "
    "--set evaluate.encoder=clip --set evaluate.encoder_model=models/clip":
        ("{command} --dry-run", "needs the InstructPix2Pix and CLIP weights"),
    "dualnerf run workflows/ablation.toml --set scene=my_capture --set edit=snow --set edit.editor=ip2p "
    "--set edit.editor_model=timbrooks/instruct-pix2pix --set edit.encoder=clip --set edit.encoder_model=models/clip "
    "--set evaluate.encoder=clip --set evaluate.encoder_model=models/clip":
        ("{command} --dry-run", "needs the InstructPix2Pix and CLIP weights"),
    "dualnerf models export-clip --from openai/clip-vit-base-patch32 --out models/clip --check":
        ("dualnerf models export-clip --help", "downloads CLIP weights from the Hugging Face hub"),
    # No Ray cluster here: the dry run expands the grid and keys it (the executor starts only after it).
    # tests/test_cluster.py runs docs/cluster.md's form of this command on a real multi-node cluster.
    "dualnerf run workflows/comparison.toml --executor ray --ray-address HEAD:6379 --cache /shared/cache "
    "--runs /shared/runs":
        ("dualnerf run workflows/comparison.toml --executor ray --ray-address HEAD:6379 --cache x --runs y --dry-run",
         "needs a Ray cluster and a shared file system"),
    # The tutorial's photos are the user's: the tiny procedural scene's images stand in for them, and the
    # reconstruction runs at a tiny scale (40 fit steps, 4 path frames; the tiny scene's 26 small views): ~40 s.
    "cp ~/photos/garden/*.jpg data/scenes/my_capture/images/":
        ("cp {photos}/*.png data/scenes/my_capture/images/", "the user's photos"),
    "dualnerf run workflows/reconstruct.toml --set scene=my_capture":
        ("{command} " + TINY_RUN, "minutes at full scale"),
}


CLUSTER_TEST_BLOCK = re.compile(r"<!-- cluster-test: [\w-]+ -->\s*```sh\n.*?```", re.DOTALL)


def _commands(path: Path) -> list[tuple[str, str]]:
    """(key, text) of each command of the file's sh blocks: continuation lines joined, the comment cut
    off; `key` is its words joined by single spaces (what REWRITES is keyed by), `text` what bash runs."""
    found = []
    text = re.sub(CLUSTER_TEST_BLOCK, "", path.read_text())
    for block in re.findall(r"```sh\n(.*?)```", text, re.DOTALL):
        for line in block.replace("\\\n", " ").splitlines():
            text = re.sub(r"\s+#.*$", "", line).strip()
            if text:
                found.append((" ".join(shlex.split(text)), text))
    return found


def _doc_files():
    return [p for p in DOCS if _commands(p)]


def _shim(tmp: Path) -> dict:
    bin_dir = tmp / "bin"
    bin_dir.mkdir()
    (bin_dir / "dualnerf").write_text(f'#!/bin/sh\nexec "{sys.executable}" -m experiments.cli "$@"\n')
    (bin_dir / "dualnerf").chmod(0o755)
    return dict(os.environ, PATH=f"{bin_dir}:{os.environ['PATH']}", PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")


def _bash(command: str, cwd: Path, env: dict, timeout: float = 600) -> subprocess.CompletedProcess:
    out = subprocess.run(["bash", "-c", f"set -eo pipefail; {command}"], cwd=cwd, env=env, capture_output=True,
                         text=True, timeout=timeout, check=False)
    assert out.returncode == 0, f"`{command}` failed ({out.returncode}):\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}"
    return out


def _make(target_args: str, sandbox: Path, env: dict) -> None:
    """`make -n` prints the recipe (from the checkout); its dualnerf commands run as dry runs."""
    recipe = subprocess.run(["make", "-n", *target_args.split()], cwd=ROOT, capture_output=True, text=True,
                            check=True).stdout
    runs = [line for line in recipe.splitlines() if line.startswith(".venv/bin/dualnerf run ")]
    assert runs, f"make -n {target_args} runs no workflow:\n{recipe}"
    for line in runs:
        _bash(line.replace(".venv/bin/dualnerf", "dualnerf") + " --dry-run", sandbox, env)
    for module in re.findall(r"-m (experiments\.\w+)", recipe):
        _bash(f'"{sys.executable}" -c "import {module}"', sandbox, env)


def test_every_sh_command_is_run_as_written_or_rewritten_with_a_reason():
    listed = {key for p in DOCS for key, _ in _commands(p)}
    unused = sorted(set(REWRITES) - listed)
    assert unused == [], f"REWRITES for commands no document has any more: {unused}"
    undecided = [c for c in listed if c not in REWRITES and (c.startswith("make ") or (
        c.startswith("dualnerf run ") and "--dry-run" not in c))]
    assert undecided == [], f"expensive doc commands without a decision in REWRITES: {undecided}"


@pytest.mark.slow
@pytest.mark.parametrize("doc", _doc_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_the_commands_of(doc, tmp_path, tiny_scene):
    sandbox = tmp_path / "work"
    sandbox.mkdir()
    (sandbox / "workflows").symlink_to(ROOT / "workflows")
    (sandbox / "docs").mkdir()
    env = _shim(tmp_path)
    for key, command in _commands(doc):
        replacement, _why = REWRITES.get(key, (command, ""))
        if replacement.startswith("@make "):
            _make(replacement[len("@make "):], sandbox, env)
            continue
        if command.startswith("mkdir -p data/scenes/my_capture"):
            _bash(command, sandbox, env)
            # The scene.toml the tutorial asks for: its first toml block.
            toml = re.search(r"```toml\n(.*?)```", doc.read_text(), re.DOTALL).group(1)
            (sandbox / "data" / "scenes" / "my_capture" / "scene.toml").write_text(toml)
            continue
        _bash(replacement.format(command=command, photos=tiny_scene / "images"), sandbox, env)
    if (sandbox / "docs" / "params.md").exists():            # `dualnerf params --markdown > docs/params.md`
        assert (sandbox / "docs" / "params.md").read_text() == (ROOT / "docs" / "params.md").read_text()
    if doc.name == "tutorial.md":                              # the reconstruction ran and reported
        assert (sandbox / "reports" / "my_capture-reconstruct" / "index.html").is_file()


def _inline_commands() -> list[tuple[str, str]]:
    found = []
    for path in DOCS:
        for span in re.findall(r"`(dualnerf [^`]+)`", path.read_text()):
            found.append((f"{path.relative_to(ROOT)}", span))
    return found


@pytest.mark.parametrize("where, span", _inline_commands(), ids=lambda x: x if "/" in x or "." in x else None)
def test_inline_commands_parse(where, span):
    """`dualnerf ...` mentioned in the text: its words are accepted by the CLI's parser (placeholders such
    as KEY, W, DIR stand for values; a command named without its arguments, `dualnerf report`, is fine)."""
    import contextlib
    import io

    from experiments.cli import build_parser

    words = shlex.split(span.replace("...", "x"))[1:]
    errors = io.StringIO()
    try:
        with contextlib.redirect_stderr(errors), contextlib.redirect_stdout(io.StringIO()):
            build_parser().parse_args(words)
    except SystemExit as exit_:
        message = errors.getvalue()
        assert exit_.code == 0 or "the following arguments are required" in message, \
            f"{where}: `{span}` is not a valid command line: {message}"


def test_relative_links_resolve():
    broken = []
    for path in DOCS:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", path.read_text()):
            if "://" in target:
                continue
            resolved = (path.parent / target).resolve()
            if not resolved.exists():
                broken.append(f"{path.relative_to(ROOT)}: {target}")
    assert broken == []


def test_citation_names_this_version_and_the_paper():
    import tomllib

    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    citation = (ROOT / "CITATION.cff").read_text()
    assert f"\nversion: {version}\n" in citation
    assert 'title: "DualNeRF: Text-Driven 3D Scene Editing via Dual-Field Representation"' in citation
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")
