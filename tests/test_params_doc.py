"""docs/params.md is what `dualnerf params --markdown` prints: the parameter reference cannot drift from the
stages' Params dataclasses (a new parameter, a changed default or comment, a stage version bump)."""
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_params_md_is_generated_from_the_stages():
    from experiments.params import markdown

    assert (ROOT / "docs" / "params.md").read_text() == markdown(), (
        "docs/params.md is out of date; regenerate it: .venv/bin/dualnerf params --markdown > docs/params.md")


def test_every_parameter_is_described():
    from experiments.params import parameters, stage_names

    missing = [f"{p.stage}.{p.name}" for stage in stage_names() for p in parameters(stage) if not p.comment]
    assert missing == [], "give these Params fields a comment (it is their documentation): " + ", ".join(missing)
