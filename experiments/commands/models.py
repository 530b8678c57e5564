"""`dualnerf models export-clip --from HUB_ID_OR_DIR --out DIR`: build the ONNX CLIP model folder that the
`clip` encoder (CCI in the edit stage, CLIP metrics in evaluate) loads with onnxruntime."""
from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers) -> None:
    parser = subparsers.add_parser("models", help="prepare model folders (CLIP export)",
                                   description="Prepare the model folders the pipeline loads.")
    sub = parser.add_subparsers(dest="models_command", metavar="SUBCOMMAND")
    export = sub.add_parser(
        "export-clip", help="export Hugging Face CLIP weights to an ONNX model folder",
        description="Export a transformers CLIPModel (hub id, e.g. openai/clip-vit-base-patch32, or a local "
                    "folder with config.json, weights and tokenizer.json) to DIR: image_encoder.onnx, "
                    "text_encoder.onnx, tokenizer.json, preprocess.json and a sha256 manifest.json. Use DIR "
                    "as encoder_model with encoder = \"clip\". Needs the `models` extra (transformers, onnx).")
    export.add_argument("--from", dest="source", required=True, metavar="HUB_ID_OR_DIR",
                        help="transformers CLIP weights: a hub id or a local folder")
    export.add_argument("--out", required=True, type=Path, metavar="DIR",
                        help="new folder to write (must not exist or be empty)")
    export.add_argument("--check", action="store_true",
                        help="after export, load the folder and compare its embeddings with the torch model's")
    export.set_defaults(handler=_export_clip)
    parser.set_defaults(handler=lambda args: (parser.print_help(), 2)[1])


def _export_clip(args: argparse.Namespace) -> int:
    from dualnerf.encoders.clip_export import export_clip

    export_clip(args.source, args.out)
    if args.check:
        from dualnerf.encoders.clip_export import check_export

        error = check_export(args.source, args.out)
        print(f"check: max |onnx - torch| embedding difference {error:.2e}")
        if error > 1e-3:
            return 1
    return 0
