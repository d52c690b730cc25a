"""One self-contained HTML report for a plan, a guidance session or a study folder.

Images are inlined as ``data:`` URIs and the style sheet is in the page: the file opens from disk
with no network. The report recognises its folder by what it holds:

* a plan folder (``plan.json``): the decision, the target in the surgeon's terms, the rendering
  and the slice contours;
* a session folder (``session.json``): its plan, then every frame — overlays, the residual, the
  flags (an unreliable frame is marked as such in red, with no residual shown as guidance),
  timings, and an evaluation against the truth where a simulation left one
  (``frame-NNN/evaluation.json``);
* anything else (a study folder): its ``*.md`` summaries, ``*.csv`` tables and ``*.png`` figures.
"""

from __future__ import annotations

import base64
import csv
import html
import json
import os
from pathlib import Path

__all__ = ["write_report"]

_STYLE = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:24px;
color:#1d1d1f;max-width:1200px}
h1{font-size:22px}h2{font-size:18px;margin-top:28px;border-bottom:1px solid #ddd}
h3{font-size:15px}
table{border-collapse:collapse;margin:8px 0}td,th{border:1px solid #ccc;padding:4px 8px;
font-size:13px;text-align:left}th{background:#f3f3f3}
img{max-width:100%;border:1px solid #ddd;margin:4px 0}
.figs{display:flex;flex-wrap:wrap;gap:12px}.figs figure{margin:0;flex:1 1 420px}
figcaption{font-size:12px;color:#555}
.ok{background:#e6f4ea;border-left:6px solid #1e8e3e;padding:8px 12px}
.bad{background:#fce8e6;border-left:6px solid #d93025;padding:12px;font-weight:600;
font-size:16px}
.guidance{font-size:18px;font-weight:600}
.muted{color:#666;font-size:12px}pre{background:#f6f6f6;padding:8px;overflow:auto}
"""


def _img(path: Path, caption: str = "") -> str:
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    cap = f"<figcaption>{html.escape(caption or path.name)}</figcaption>"
    alt = html.escape(path.name)
    return f'<figure><img alt="{alt}" src="data:image/png;base64,{data}">{cap}</figure>'


def _table(rows: list[list], header: list[str]) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows
    )
    return f"<table><tr>{head}</tr>{body}</table>"


def _fmt(x) -> str:
    return f"{x:.2f}" if isinstance(x, float) else str(x)


def _plan_section(folder: Path, plan: dict) -> str:
    parts = [f"<h2>Plan</h2><p class='muted'>{html.escape(str(folder))}; CT "
             f"{html.escape(plan['ct']['path'])} ({' x '.join(map(str, plan['ct']['shape']))})</p>",
             f"<p>{html.escape(plan.get('decision', {}).get('description', ''))}</p>"]  # fmt: skip
    rows = [[b, r["description"], _fmt(r["distance_mm"]), _fmt(r["angle_deg"])]
            for b, r in plan.get("residual_in_ct", {}).items()]  # fmt: skip
    if rows:
        parts.append("<h3>Reduction planned (as seen in the CT)</h3>")
        parts.append(_table(rows, ["bone", "to reach the target", "mm", "deg"]))
    figs = [_img(folder / n, c) for n, c in (("rendering.png", "current (orange), target (green)"),
                                            ("contours.png", "bones on the CT"))
            if (folder / n).is_file()]  # fmt: skip
    parts.append(f"<div class='figs'>{''.join(figs)}</div>")
    parts.append(f"<p class='muted'>{html.escape(plan.get('method', ''))}. Model: "
                 f"{html.escape(str(plan.get('model', {}).get('doi', '')))}, "
                 f"{html.escape(str(plan.get('model', {}).get('note', '')))}</p>")  # fmt: skip
    return "".join(parts)


def _frame_section(folder: Path) -> str:
    r = json.loads((folder / "result.json").read_text())
    title = f"<h2>Frame {r['frame']} <span class='muted'>({r['mode']}, {r['time']})</span></h2>"
    if r.get("reliable"):
        flag = "<div class='ok'>Registration converged.</div>"
        guidance = "".join(
            f"<p class='guidance'>{html.escape(b)}: {html.escape(x['description'])}</p>"
            for b, x in r["residual"].items()
        )
    else:
        warnings = "; ".join(r.get("warnings", [])) or "the registration did not converge"
        likely = " Likely wrong: its joints are ones no dislocation gives." if r.get(
            "verdict") == "implausible" else ""  # fmt: skip
        flag = (f"<div class='bad'>UNRELIABLE REGISTRATION: not guidance.{likely} "
                f"{html.escape(warnings)}</div>")  # fmt: skip
        guidance = ""
    rows = [[b, _fmt(x["distance_mm"]), _fmt(x["angle_deg"]),
             ", ".join(f"{v:+.1f}" for v in x["translation_mm"]),
             ", ".join(f"{v:+.1f}" for v in x["rotation_deg"])]
            for b, x in r["residual"].items()]  # fmt: skip
    table = _table(rows, ["bone", "residual mm", "residual deg", "x y z mm (L P S)",
                          "rotation deg"]) if rows and r.get("reliable") else ""  # fmt: skip
    stages = ", ".join(f"{s['name']} {s['seconds']:.1f} s" for s in r.get("stages", []))
    timing = (f"<p class='muted'>similarity {r.get('similarity', float('nan')):.3f}; "
              f"{r.get('seconds', 0):.1f} s ({stages})</p>")  # fmt: skip
    evaluation = ""
    if (folder / "evaluation.json").is_file():
        ev = json.loads((folder / "evaluation.json").read_text())
        evaluation = "<h3>Against the known truth (simulation)</h3>" + _table(
            [[k, _fmt(v)] for k, v in ev.items()], ["measure", "value"]
        )
    overlays = [_img(p, p.stem.replace("overlay_", "view ") + ": registered (yellow), target "
                     "(green)") for p in sorted(folder.glob("overlay_*.png"))]  # fmt: skip
    return (title + flag + guidance + table + timing + evaluation
            + f"<div class='figs'>{''.join(overlays)}</div>")  # fmt: skip


def _study_section(folder: Path) -> str:
    parts = [f"<h2>{html.escape(folder.name)}</h2>"]
    for md in sorted(folder.glob("*.md")):
        parts.append(f"<h3>{html.escape(md.name)}</h3><pre>{html.escape(md.read_text())}</pre>")
    for table in sorted(folder.glob("*.csv")):
        with open(table, newline="") as fh:
            rows = list(csv.reader(fh))
        if rows:
            more = f"<p class='muted'>{len(rows) - 201} more rows in {table.name}</p>" \
                if len(rows) > 201 else ""  # fmt: skip
            parts.append(f"<h3>{html.escape(table.name)}</h3>{_table(rows[1:201], rows[0])}{more}")
    figs = [_img(p) for p in sorted(folder.glob("*.png"))]
    parts.append(f"<div class='figs'>{''.join(figs)}</div>")
    return "".join(parts)


def write_report(folder: str | os.PathLike, out: str | os.PathLike | None = None) -> Path:
    """Write ``folder/report.html`` (or ``out``) for a plan, session or study folder.

    Raises
    ------
    ValueError
        A folder that does not exist, or a session whose plan folder is gone.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder}: not a folder")
    if (folder / "session.json").is_file():
        session = json.loads((folder / "session.json").read_text())
        plan_dir = Path(session["plan"])
        if not (plan_dir / "plan.json").is_file():
            raise ValueError(f"{folder}: the session's plan {plan_dir} is gone")
        body = (f"<h1>pelvicnav guidance session</h1><p class='muted'>{html.escape(str(folder))}"
                f", {len(session['frames'])} frame(s)</p>")  # fmt: skip
        body += _plan_section(plan_dir, json.loads((plan_dir / "plan.json").read_text()))
        summary = [[f["frame"], f["mode"], "yes" if f["reliable"] else "NO — not guidance",
                    "; ".join(f["residual"].values()) if f["reliable"] else "",
                    f"{f['seconds']:.1f}"] for f in session["frames"]]  # fmt: skip
        body += "<h2>Frames</h2>" + _table(summary, ["frame", "mode", "reliable", "residual", "s"])
        for f in reversed(session["frames"]):
            body += _frame_section(folder / f["folder"])
        title = "pelvicnav session"
    elif (folder / "plan.json").is_file():
        body = "<h1>pelvicnav plan</h1>" + _plan_section(
            folder, json.loads((folder / "plan.json").read_text())
        )
        title = "pelvicnav plan"
    else:
        body = "<h1>pelvicnav study</h1>" + _study_section(folder)
        title = f"pelvicnav study {folder.name}"
    page = (f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
            f"<title>{html.escape(title)}</title><style>{_STYLE}</style></head><body>{body}"
            "<p class='muted'>pelvicnav research software, not for clinical use.</p>"
            "</body></html>")  # fmt: skip
    path = Path(out) if out is not None else folder / "report.html"
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(page, encoding="utf-8")
    os.replace(tmp, path)
    return path
