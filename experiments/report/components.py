"""The report's component section: what switching one of DF, SA, CCI on changes, per failure-mode setting.

The differences to the reference row (differences.py) compare every row with Instruct-NeRF2NeRF; a claim
about one component needs the row with it against the row without it, everything else equal. For every
IDU row with a component on, its partner is the row of equal parameters (e.g. the emulator's failure-mode
axes `lock_in`, `cast`) whose flags differ in that component only: DF+SA vs DF, DF+SA+CCI vs DF+CCI, ...
The difference is paired over the (scene, edit, seed) units both ran, with the paired 95% t interval, so
a workflow that crosses components with failure modes (workflows/ablation_failure_modes.toml) shows
whether, e.g., SA helps only where lock-in is on. Rows without a partner are left out.
"""
from __future__ import annotations

import html

from dualnerf.metrics import METRICS
from experiments import statistics as S
from experiments.methods import FLAGS
from experiments.report.differences import diff_json, format_diff, unit_values
from experiments.report.rows import display_label, metric_value, row_key

# The joint edit-quality columns (issue 29: whole-image PSNR to the ground-truth edit first, in-mask and
# outside-mask beside it, so editing less cannot pass as preserving more); the CLIP-space directional
# similarity where a scene has no ground truth.
COLUMNS = ("gt_psnr_edit", "gt_psnr_inside", "gt_psnr_background", "gt_lpips_edit", "clip_text_image_direction")


def component_effects(rows, docs, table, columns) -> list[dict]:
    """One entry per (component, row with it, partner without it), in FLAGS then table order."""
    shown = [c for c in COLUMNS if c in columns]
    if not shown:
        return []
    by_flags = {(trow.method.flags, tuple(trow.params)): trow for trow in table
                if trow.method.flags is not None}
    values = {c: unit_values(rows, docs, c, metric_value) for c in shown}
    entries = []
    for index, component in enumerate(FLAGS):
        for trow in table:
            flags = trow.method.flags
            if flags is None or not flags[index]:
                continue
            without = tuple(f and i != index for i, f in enumerate(flags))
            partner = by_flags.get((without, tuple(trow.params)))
            if partner is None:
                continue
            diffs = {c: S.paired_difference(values[c][row_key(trow)], values[c][row_key(partner)]) for c in shown}
            entries.append({"component": component, "row": trow.label, "partner": partner.label,
                            "params": [list(p) for p in trow.params],
                            "pairs": max(d.n_pairs for d in diffs.values()),
                            "differences": diffs})
    return entries


def entries_json(entries: list[dict]) -> list[dict]:
    return [{**{k: v for k, v in e.items() if k != "differences"},
             "differences": {c: diff_json(d) for c, d in e["differences"].items()}} for e in entries]


def _setting(entry: dict) -> str:
    return ", ".join(f"{k}={v}" for k, v in entry["params"]) or "-"


CAPTION = ("Each component switched on against the row without it, all else equal (same failure-mode "
           "setting): mean paired difference over the (scene, edit, seed) units both ran, with its paired "
           "95% t interval; 'excl. 0': beyond seed noise at this n. A component's claim holds where its "
           "difference excludes 0 with its failure mode on and not with it off (the control).")


def markdown_section(entries: list[dict]) -> list[str]:
    if not entries:
        return []
    shown = list(entries[0]["differences"])
    lines = ["", "## Component effects by failure-mode setting", "",
             "| Component | Comparison | Setting | pairs | " + " | ".join(f"Δ {METRICS[c].symbol}" for c in shown)
             + " |", "|---|---|---|---:|" + "---:|" * len(shown)]
    for e in entries:
        lines.append(f"| {e['component']} | {e['row']} − {e['partner']} | {_setting(e)} | {e['pairs']} | "
                     + " | ".join(format_diff(e["differences"][c], c) for c in shown) + " |")
    return lines + ["", CAPTION]


def html_section(entries: list[dict]) -> str:
    if not entries:
        return ""
    esc = html.escape
    shown = list(entries[0]["differences"])
    parts = [("<h2>Component effects by failure-mode setting</h2><table class='paired'><tr><th>Component</th>"
              "<th>Comparison</th><th>Setting</th><th>pairs</th>")]
    parts += [f"<th>Δ {esc(METRICS[c].symbol)}</th>" for c in shown]
    parts.append("</tr>")
    for e in entries:
        parts.append(f"<tr><td style='text-align:left'>{esc(e['component'])}</td><td style='text-align:left'>"
                     f"{esc(display_label(e['row'], ()))} − {esc(e['partner'])}</td><td>{esc(_setting(e))}</td>"
                     f"<td>{e['pairs']}</td>")
        for c in shown:
            diff = e["differences"][c]
            cls = " class='ns'" if diff.excludes_zero is False else ""
            parts.append(f"<td{cls}>{esc(format_diff(diff, c))}</td>")
        parts.append("</tr>")
    parts.append(f"</table><p>{esc(CAPTION)}</p>")
    return "".join(parts)
