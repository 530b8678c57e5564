"""The report's index.html: the title block (which editor and encoder, simulators named as such), the
metrics table, the statistics sections, views, curves and videos; relative links only."""
from __future__ import annotations

import html
from pathlib import Path

from experiments.report import differences as RS
from experiments.report.rows import display_label
from experiments.report.tables import column_header, format_cell

SIMULATED_EDITORS = {"synthetic"}
SIMULATED_ENCODERS = {"proxy"}


def _identities(docs: list[dict], key: str) -> list[str]:
    found = set()
    for doc in docs:
        entry = doc.get(key) or {}
        if entry.get("kind"):
            found.add(entry["kind"])
    return sorted(found)


def title_rows(docs: list[dict], title_info: dict) -> list[tuple[str, str]]:
    editors = _identities(docs, "editor") or ["none (no edited rows)"]
    encoders = _identities(docs, "encoder") or ["unknown"]
    editor_text = ", ".join(f"{e} (InstructPix2Pix EMULATOR, not IP2P)" if e in SIMULATED_EDITORS else e
                            for e in editors)
    encoder_text = ", ".join(f"{e} (weight-free stand-in, NOT CLIP)" if e in SIMULATED_ENCODERS else e
                             for e in encoders)
    rows = [(str(k), str(v)) for k, v in title_info.items()]
    lpips = sorted({(doc.get("lpips") or {}).get("tag") for doc in docs} - {None})
    return rows + [("editor", editor_text), ("encoder", encoder_text)] + \
        ([("LPIPS metrics", ", ".join(lpips) + " (pretrained, v0.1 linear layers)")] if lpips else [])


def metrics_table_html(columns, table, docs) -> list[str]:
    esc = html.escape
    parts = ["<table><tr><th>Variant</th><th>DF</th><th>SA</th><th>CCI</th><th>seeds</th><th>n</th>"]
    parts += [f"<th>{esc(column_header(c, docs))}</th>" for c in columns]
    parts.append("</tr>")
    for row in table:
        label = display_label(row.label, row.params, original=row.method.is_original)
        seeds = ", ".join("-" if s is None else str(s) for s in row.seeds)
        parts.append(f"<tr><td style='text-align:left'>{esc(label)}</td>"
                     + "".join(f"<td style='text-align:center'>{mark}</td>" for mark in row.method.marks())
                     + f"<td>{esc(seeds)}</td><td>{row.runs}</td>")
        for c in columns:
            cls = " class='best'" if row.best[c] else ""
            parts.append(f"<td{cls}>{esc(format_cell(row, c))}</td>")
        parts.append("</tr>")
    parts.append("</table>")
    return parts


def write_html(out_dir: Path, *, title_rows, columns, table, docs, grid_labels, strip_labels, curves,
               videos, sections=()) -> Path:
    """index.html; `sections` are ready HTML fragments (statistics) placed after the metrics table."""
    esc = html.escape
    parts = ["<!DOCTYPE html>", "<html><head><meta charset='utf-8'><title>DualNeRF report</title>",
             ("<style>body{font-family:sans-serif;margin:2em;max-width:1200px}"
             "table{border-collapse:collapse;display:block;overflow-x:auto;max-width:100%}"
             "td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}th{background:#eee}"
             ".best{font-weight:bold;background:#e6f4e6}.warn{color:#a00;font-weight:bold}.ns{color:#777}.paired td{white-space:nowrap}"
             "img{max-width:100%}</style></head><body>"), "<h1>DualNeRF experiment report</h1>",
             "<table class='title'>"]
    for key, value in title_rows:
        cls = " class='warn'" if ("EMULATOR" in value or "NOT CLIP" in value) else ""
        parts.append(f"<tr><th>{esc(key)}</th><td{cls} style='text-align:left'>{esc(value)}</td></tr>")
    parts.append("</table>")
    parts.append("<h2>Metrics</h2>")
    parts += metrics_table_html(columns, table, docs)
    parts.append("<p>Mean ± sample std over seeds; n: results per row. Best value per column highlighted. "
                 "Downloads: <a href='table.md'>table.md</a>, "
                 "<a href='table.csv'>table.csv</a>, <a href='table.json'>table.json</a>. Metric "
                 "definitions: docs/metrics.md in the repository.</p>")
    parts += list(sections)
    if grid_labels:
        parts.append(f"<h2>Views</h2><p>Rows: {esc(', '.join(grid_labels))}.</p>"
                     "<img src='grid.png' alt='image grid'>")
    if strip_labels:
        parts.append(f"<h2>Camera path</h2><p>Rows: {esc(', '.join(strip_labels))}.</p>"
                     "<img src='path_strip.png' alt='camera path frames'>")
    if curves:
        parts.append("<h2>Training curves</h2>")
        parts += [f"<img src='{esc(rel)}' alt='{esc(rel)}'>" for rel in curves]
    if videos:
        parts.append("<h2>Camera-path videos</h2>")
        for label, rel in videos:
            parts.append(f"<figure><figcaption>{esc(label)}</figcaption><video controls loop "
                         f"src='{esc(rel)}' width='480'></video><br><a href='{esc(rel)}'>{esc(rel)}</a>"
                         f"</figure>")
    parts.append("</body></html>")
    path = out_dir / "index.html"
    path.write_text("\n".join(parts) + "\n")
    return path


def statistics_html(columns, table, docs, paired, reference, per_scene, param_plots) -> list[str]:
    esc = html.escape
    parts = []
    if paired:
        headers = [column_header(c, docs) for c in columns]
        parts.append(RS.html_section(table, columns, headers, paired, reference))
    if param_plots:
        parts.append("<h2>Parameter axes</h2><p>Each metric against the parameter: mean ± std over seeds "
                     "(error bars), averaged over scenes and edits.</p>")
        parts += [f"<img src='{esc(rel)}' alt='{esc(rel)}'>" for rel in param_plots]
    if per_scene:
        parts.append("<h2>Per scene and edit</h2>")
        for scene, edit, rel, sub_columns, sub_table, sub_docs, sub_paired, label, _ in per_scene:
            parts.append(f"<h3>{esc(scene)} / {esc(edit)}</h3>")
            parts += metrics_table_html(sub_columns, sub_table, sub_docs)
            if sub_paired:
                headers = [column_header(c, sub_docs) for c in sub_columns]
                parts.append(RS.html_section(sub_table, sub_columns, headers, sub_paired, label)
                             .replace("<h2>", "<h4>").replace("</h2>", "</h4>"))
            parts.append(f"<p>Downloads: <a href='{esc(rel)}/table.md'>table.md</a>, "
                         f"<a href='{esc(rel)}/table.csv'>table.csv</a>, "
                         f"<a href='{esc(rel)}/table.json'>table.json</a>.</p>")
    return parts
