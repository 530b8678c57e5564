"""The experiment layer: what turns stages into experiments.

    workflow/   a TOML grid (scenes x edits x methods x seeds x parameter axes) -> steps (docs/workflows.md)
    methods     Method: IN2N, DualNeRF, DF/SA/CCI combinations, the per-frame baseline, the unedited scene
    report/     tables, statistics, image grids, curves and index.html of a finished workflow
    statistics  mean ± std over seeds, paired differences with bootstrap intervals (pure numpy)
    cli, commands/   the `dualnerf` command line
    check_smoke the acceptance check of `make smoke`

Layering (tests/test_import_graph.py): `dualnerf/` (the model library) and `pipeline/` (the generic
engine) import none of the others; `stages/` (one module per stage, plus what stages share) imports
those two; this package may import all three, and nothing but tests and benchmarks imports it.
"""
