"""The summary files of `mosaic batch` in OUT_DIR: summary.csv (a row per video, `COLUMNS`),
summary.json (the same rows, the batch's meta and counts, the patients' comparisons) and
index.html (`render_index`: one self-contained page, sortable, a thumbnail per video).
"""

from __future__ import annotations

import csv
import html
import io
import math
from pathlib import Path
from typing import Any
from urllib.parse import quote

from mosaic.batch_video import FAILED, INTERRUPTED, NOT_RUN, OK
from mosaic.io import write_json, write_text

#: Columns of summary.csv (summary.json has the same keys per video).
COLUMNS = (
    "id",
    "status",
    "frames",
    "registered",
    "registered_pct",
    "frames_until_failure",
    "segments",
    "fps",
    "time_s",
    "error",
    "video",
    "mosaic",
    "report",
    "resumed",
)
VISIT_COLUMNS = ("patient", "visit")  # summary.csv's extra columns when patients are named
COMPARISONS = "compare"  # OUT_DIR/compare/<patient>/<visit>/: visits on their first's map


def status_counts(rows: list[dict[str, Any]]) -> dict[str, int]:
    """How many rows have each status (every status, in the summary's order)."""
    return {s: sum(r["status"] == s for r in rows) for s in (OK, FAILED, INTERRUPTED, NOT_RUN)}


def write_summary(
    out: Path,
    rows: list[dict[str, Any]],
    meta: dict[str, Any],
    patients: dict[str, Any] | None = None,
) -> None:
    """summary.csv, summary.json and index.html in `out`, each written atomically; with the
    patients' comparisons (`compare_patients`), their entries and table too."""
    buffer = io.StringIO()
    columns = COLUMNS + VISIT_COLUMNS if any("patient" in r for r in rows) else COLUMNS
    writer = csv.DictWriter(buffer, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if row.get(k) is None else row[k] for k in columns})
    write_text(out / "summary.csv", buffer.getvalue())
    counts = status_counts(rows)
    summary = {"meta": meta, "counts": counts, "videos": rows}
    write_json(out / "summary.json", summary | ({"patients": patients} if patients else {}))
    write_text(out / "index.html", render_index(rows, meta, counts, patients))


_STATUS_ORDER = {FAILED: 0, INTERRUPTED: 1, NOT_RUN: 2, OK: 3}
_HTML_COLUMNS = (  # (key, header, numeric)
    ("status", "status", False),
    ("id", "video", False),
    ("frames", "frames", True),
    ("registered_pct", "registered %", True),
    ("frames_until_failure", "until failure", True),
    ("segments", "segments", True),
    ("fps", "frames/s", True),
    ("time_s", "time s", True),
    ("error", "error", False),
)
_STYLE = """
body{font-family:system-ui,sans-serif;margin:1.5em;color:#222}
table{border-collapse:collapse}th,td{padding:4px 8px;border-bottom:1px solid #ddd;
vertical-align:middle;text-align:left}th{cursor:pointer;background:#f4f4f4;position:sticky;top:0}
th:hover{background:#e8e8e8}td.n{text-align:right;font-variant-numeric:tabular-nums}
tr.failed td,tr.interrupted td{background:#fdecea}tr.not.run td{color:#888}
img{max-width:160px;max-height:120px;display:block}.err{color:#a00;max-width:40em}
"""
_SCRIPT = """
document.querySelectorAll('th').forEach(function(th, col){
  th.addEventListener('click', function(){
    var body = th.closest('table').tBodies[0];
    var asc = th.dataset.dir !== 'asc';
    th.parentNode.querySelectorAll('th').forEach(function(h){ delete h.dataset.dir; });
    th.dataset.dir = asc ? 'asc' : 'desc';
    var rows = Array.prototype.slice.call(body.rows);
    rows.sort(function(a, b){
      var x = a.cells[col].dataset.v, y = b.cells[col].dataset.v;
      var nx = parseFloat(x), ny = parseFloat(y);
      var c = (!isNaN(nx) && !isNaN(ny)) ? nx - ny : x.localeCompare(y);
      return asc ? c : -c;
    });
    rows.forEach(function(r){ body.appendChild(r); });
  });
});
"""


def _cell(row: dict[str, Any], key: str, numeric: bool) -> str:
    value = row.get(key)
    if key == "status":
        sort = str(_STATUS_ORDER.get(value, 9))
    elif value is None or (isinstance(value, float) and math.isnan(value)):
        sort = "" if not numeric else "-1"
    else:
        sort = str(value)
    text = "" if value is None else str(value)
    if key == "id":
        inner = html.escape(text)
        if row.get("report"):
            inner = f'<a href="{quote(row["report"])}">{inner}</a>'
        if row.get("log"):
            inner += f' <small>(<a href="{quote(row["log"])}">log</a>)</small>'
        body = inner
    else:
        body = html.escape(text)
    klass = ' class="n"' if numeric else ' class="err"' if key == "error" else ""
    return f'<td{klass} data-v="{html.escape(sort)}">{body}</td>'


def render_index(
    rows: list[dict[str, Any]],
    meta: dict[str, Any],
    counts: dict[str, int],
    patients: dict[str, Any] | None = None,
) -> str:
    """The browsable summary: one self-contained page (inline style and script, no server),
    a thumbnail per video linked to its mosaic, failed videos first, sortable by any column;
    with `patients`, then each patient's visits side by side with their change maps."""
    ordered = sorted(
        enumerate(rows), key=lambda item: (_STATUS_ORDER.get(item[1]["status"], 9), item[0])
    )
    head = "<th data-v>mosaic</th>" + "".join(
        f"<th>{html.escape(title)}</th>" for _, title, _ in _HTML_COLUMNS
    )
    lines = []
    for _, row in ordered:
        thumb = ""
        if row.get("thumbnail") and row.get("mosaic"):
            thumb = (
                f'<a href="{quote(row["mosaic"])}"><img src="{quote(row["thumbnail"])}" '
                f'alt="{html.escape(row["id"])}" loading="lazy"></a>'
            )
        cells = "".join(_cell(row, key, numeric) for key, _, numeric in _HTML_COLUMNS)
        status = html.escape(row["status"])
        lines.append(f'<tr class="{status}"><td data-v="">{thumb}</td>{cells}</tr>')
    tally = ", ".join(f"{n} {html.escape(s)}" for s, n in counts.items() if n)
    when = html.escape(str(meta.get("finished") or meta.get("started") or ""))
    title = f"mosaic batch: {html.escape(str(meta.get('input', '')))}"
    return (
        "<!DOCTYPE html>\n"
        f'<html lang="en"><head><meta charset="utf-8"><title>{title}</title>'
        f"<style>{_STYLE}</style></head><body>\n"
        f"<h1>{title}</h1>\n<p>{len(rows)} videos: {tally}. Engine "
        f"{html.escape(str(meta.get('engine', '')))}; {when}. Click a column to sort.</p>\n"
        f"<table><thead><tr>{head}</tr></thead><tbody>\n"
        + "\n".join(lines)
        + "\n</tbody></table>\n"
        + _visits_section(patients)
        + f"<script>{_SCRIPT}</script>\n</body></html>\n"
    )


def _visits_section(patients: dict[str, Any] | None) -> str:
    """Each patient's row of visits (`compare.patients_table`), or nothing."""
    if not patients:
        return ""
    from mosaic.compare import patients_table

    return "<h2>Visits compared</h2>\n" + patients_table(patients, root=f"{COMPARISONS}/")
