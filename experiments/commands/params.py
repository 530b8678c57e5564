"""`dualnerf params [STAGE]`: each stage parameter's type, default, description (from the stage's Params
dataclass and its source comments), whether it enters the cache key and whether the workflow sets it."""
from __future__ import annotations

import argparse


class ParamsCommandError(ValueError):
    user_error = True


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "params", help="list the stages' parameters: type, default, description, key",
        description="List the parameters of one stage (or of all): `<stage>.<param> = default (type; notes)` "
                    "and the description from the source. Set them with --set <stage>.<param>=VALUE or in "
                    "a workflow's [stages.<stage>] table.")
    parser.add_argument("stage", nargs="?", help="a stage name (default: every stage)")
    parser.add_argument("--markdown", action="store_true", help="print docs/params.md (every stage) instead")
    parser.set_defaults(handler=_params)


def _params(args: argparse.Namespace) -> int:
    from experiments.params import markdown, stage_names, text

    if args.markdown:
        print(markdown(), end="")
        return 0
    names = stage_names()
    if args.stage is not None and args.stage not in names:
        raise ParamsCommandError(f"unknown stage '{args.stage}'; the stages are {', '.join(names)}.")
    print("\n\n".join(text(name) for name in ([args.stage] if args.stage else names)))
    return 0
