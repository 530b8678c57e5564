"""In-stage checkpoints of a growing list of images (evaluate's renders, the per-frame baseline's edits):
each checkpoint holds every image so far as a lossless PNG, so a resumed run continues with identical
images and publishes the same result. Checkpoint folders come from the engine (StageContext.checkpoint:
written aside, renamed into place, checksummed)."""
from __future__ import annotations

import json

from stages.images import read_png, write_png

DETAILS = "details.json"


def save_images(ctx, images: list, details: list | None = None) -> None:
    """A checkpoint at step len(images): every image, and one JSON-serialisable entry per image."""
    with ctx.checkpoint(len(images)) as folder:
        for k, image in enumerate(images):
            write_png(folder / f"{k:05d}.png", image)
        if details is not None:
            (folder / DETAILS).write_text(json.dumps(details))


def resume_images(ctx, total: int, sizes: list[tuple[int, int]] | None = None, with_details: bool = False,
                  restart: str = "starting over") -> tuple[list, list]:
    """(images, details) of the newest checkpoint, at most `total` of them, if they fit this run (every
    image readable, with `sizes` of its (width, height), with `with_details` one detail entry each);
    else ([], []) with a warning that ends in `restart`."""
    latest = ctx.latest_checkpoint()
    if latest is None:
        return [], []
    step, folder = latest
    count = min(step, total)
    details = json.loads((folder / DETAILS).read_text()) if (folder / DETAILS).is_file() else []
    images = []
    for k in range(count):
        image = read_png(folder / f"{k:05d}.png")
        if image is None or (sizes is not None and (image.shape[1], image.shape[0]) != tuple(sizes[k])):
            break
        images.append(image)
    if len(images) < count or (with_details and len(details) < count):
        ctx.log.warning("checkpoint %s does not match this run's images; %s", folder, restart)
        return [], []
    return images, details[:count]
