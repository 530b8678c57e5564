"""`dualnerf scene NAME --out DIR`: render a procedural (synthetic) scene with its ground-truth edits;
`dualnerf scene list`: the scenes and their edits."""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "scene", help="render a procedural test scene (synthetic) with ground-truth edits",
        description="Render a procedural scene: synthetic views from a ray caster (not photographs), its "
                    "edit vocabulary (scene.toml) and 3D-consistent ground-truth edited views and masks.")
    parser.add_argument("name", nargs="?", help="scene name, or 'list' to list the scenes and their edits")
    parser.add_argument("--out", type=Path, metavar="DIR", help="output folder (must not exist or be empty)")
    parser.add_argument("--list", action="store_true", help=argparse.SUPPRESS)     # older spelling of `list`
    parser.add_argument("--seed", type=int, default=0, help="texture seed (default 0)")
    parser.add_argument("--format", choices=("scene", "nerfstudio"), default="scene",
                        help="'nerfstudio' also writes a top-level transforms.json for the import path")
    parser.add_argument("--width", type=int, help="image width (default: the scene's)")
    parser.add_argument("--height", type=int, help="image height (default: the scene's)")
    parser.add_argument("--n-views", type=int, help="number of views (default: the scene's)")
    parser.add_argument("--supersample", type=int, help="samples per pixel side (default: the scene's)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                        help="render processes (default: all cores)")
    parser.set_defaults(handler=_scene)


class SceneCommandError(ValueError):
    user_error = True


def _scene(args: argparse.Namespace) -> int:
    from dualnerf.scenes import SCENES, generate_scene, scene_config
    from dualnerf.scenes.generate import BUILDERS

    if args.list or args.name == "list":
        for name in SCENES:
            c = SCENES[name]
            edits = ", ".join(f"{e.id} ({e.kind})" for e in BUILDERS[name][1])
            rig = "360 deg orbit" if c.arc_degrees >= 360 else f"{c.arc_degrees:.0f} deg arc"
            print(f"{name:10s} {c.n_views} views {c.width}x{c.height} {rig:14s} edits: {edits}")
        return 0
    if not args.name or args.out is None:
        raise SceneCommandError("give a scene name and --out DIR, e.g. `dualnerf scene campsite --out "
                                "data/campsite` (`dualnerf scene list` shows the scenes).")
    if args.out.exists() and any(args.out.iterdir()):
        raise SceneCommandError(f"{args.out} exists and is not empty; choose a new folder or remove it.")
    overrides = {k: v for k, v in (("width", args.width), ("height", args.height), ("n_views", args.n_views),
                                   ("supersample", args.supersample)) if v is not None}
    config = scene_config(args.name, **overrides)
    print(f"SYNTHETIC procedural scene '{args.name}': {config.n_views} views {config.width}x{config.height} "
          f"rendered by a ray caster (not photographs)", file=sys.stderr)
    start = time.perf_counter()

    def progress(done: int, total: int) -> None:
        if not args.quiet:
            print(f"\r  view {done}/{total}", end="" if done < total else "\n", file=sys.stderr, flush=True)

    generate_scene(args.name, args.out, seed=args.seed, format=args.format, workers=max(1, args.workers),
                   progress=progress, **overrides)
    print(f"wrote {args.out} in {time.perf_counter() - start:.1f} s", file=sys.stderr)
    return 0
