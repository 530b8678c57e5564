"""`python -m experiments.check_smoke REPORT_DIR`: the smoke run's acceptance check (used by `make smoke`).

Fails (exit 1, naming what is wrong) unless the report has index.html, the grid and a table whose every
row has a finite value in every metric column that applies to it, and browser-playable videos."""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path


def problems(report_dir: Path) -> list[str]:
    found = []
    for name in ("index.html", "table.md", "table.csv", "table.json", "grid.png"):
        if not (report_dir / name).is_file():
            found.append(f"{report_dir / name} is missing")
    if found:
        return found
    table = json.loads((report_dir / "table.json").read_text())
    if len(table["rows"]) < 2:
        found.append(f"table.json has {len(table['rows'])} rows; expected the original plus edited rows")
    for row in table["rows"]:
        for column, cell in row["metrics"].items():
            value = cell["mean"]
            original_only_gap = row["kind"] == "original" and value is None
            if original_only_gap:
                continue      # e.g. edit-vs-original metrics are undefined for the original row
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                found.append(f"row '{row['label']}': metric {column} is {value!r}, not a finite number")
    found += _video_problems(report_dir)
    return found


def _video_problems(report_dir: Path) -> list[str]:
    """Every camera-path video must be what browsers play: H.264 in yuv420p with at least one frame."""
    from dualnerf.video import probe_video

    found = []
    for path in sorted((report_dir / "videos").glob("*.mp4")):
        info = probe_video(path)
        if (info["codec"], info["pix_fmt"]) != ("h264", "yuv420p") or info["frames"] < 1:
            found.append(f"{path} is {info['codec']}/{info['pix_fmt']} with {info['frames']} frames; "
                         f"browsers need h264/yuv420p (rerun evaluate, version 3 writes it)")
    return found


def main(argv: list[str]) -> int:
    report_dir = Path(argv[0] if argv else "reports/smoke")
    found = problems(report_dir)
    for line in found:
        print(f"smoke check: {line}", file=sys.stderr)
    if not found:
        print(f"smoke check: {report_dir} complete, all metrics finite")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
