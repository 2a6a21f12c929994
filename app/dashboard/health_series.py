"""The dashboard's calibration-health section: status, reasons and the time series of the
rolling window's ECE and served-ellipse coverage per level (hand-written inline SVG: no
plotting library on this path)."""

from __future__ import annotations

import html
from collections.abc import Sequence
from typing import Any

#: Line colours of the series: ECE, then one per level.
COLORS = ("#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b")
WIDTH, HEIGHT, PAD = 520, 180, 36


def _polyline(xs: Sequence[float], ys: Sequence[float | None], x_max: float, color: str,
              dashed: bool = False) -> str:
    points = " ".join(
        f"{PAD + (WIDTH - 2 * PAD) * x / x_max:.1f},{HEIGHT - PAD - (HEIGHT - 2 * PAD) * y:.1f}"
        for x, y in zip(xs, ys, strict=True) if y is not None)
    dash = " stroke-dasharray='4 3'" if dashed else ""
    return (f"<polyline fill='none' stroke='{color}' stroke-width='1.5'{dash} "
            f"points='{points}'/>")


def series_svg(series: list[dict[str, Any]], levels: Sequence[float]) -> str:
    """Window ECE and coverage per level (0..1) against feedback frames, with the nominal
    levels dashed."""
    xs = [p["frames_total"] for p in series]
    x_max = max(xs[-1], 1)
    lines = [_polyline(xs, [p["ece"] for p in series], x_max, COLORS[0])]
    legend = [("ECE", COLORS[0])]
    for j, level in enumerate(levels):
        color = COLORS[1 + j % (len(COLORS) - 1)]
        lines.append(_polyline(xs, [p["coverage"][j] for p in series], x_max, color))
        lines.append(_polyline([0, x_max], [level, level], x_max, color, dashed=True))
        legend.append((f"coverage {level:g}", color))
    keys = "".join(f"<text x='{PAD + 96 * i}' y='14' fill='{c}' font-size='10'>{html.escape(t)}"
                   f"</text>" for i, (t, c) in enumerate(legend))
    axes = (f"<line x1='{PAD}' y1='{HEIGHT - PAD}' x2='{WIDTH - PAD}' y2='{HEIGHT - PAD}' "
            f"stroke='#888'/><line x1='{PAD}' y1='{PAD}' x2='{PAD}' y2='{HEIGHT - PAD}' "
            f"stroke='#888'/><text x='{PAD - 4}' y='{PAD + 4}' font-size='9' "
            f"text-anchor='end'>1</text><text x='{PAD - 4}' y='{HEIGHT - PAD}' font-size='9' "
            f"text-anchor='end'>0</text><text x='{WIDTH - PAD}' y='{HEIGHT - PAD + 14}' "
            f"font-size='9' text-anchor='end'>{x_max} feedback frames</text>")
    return (f"<svg class='plot health-series' xmlns='http://www.w3.org/2000/svg' "
            f"width='{WIDTH}' height='{HEIGHT}' viewBox='0 0 {WIDTH} {HEIGHT}'>{keys}{axes}"
            + "".join(lines) + "</svg>")


def health_section(doc: dict[str, Any]) -> str:
    """The HTML of a health document (`app.health_document`)."""
    status = doc["status"]
    cls = {"ok": "ok", "degraded": "bad"}.get(status, "note")
    win = doc["window"]
    ece = win["ece"]["value"]
    head = (f"<p><b>{html.escape(doc['profile']['id'])}</b>: <span class='{cls}'>"
            f"{html.escape(status)}</span> · window {win['frames']} frames, {win['tp']} TPs, "
            f"ECE {'—' if ece is None else f'{ece:.4f}'} · since activation "
            f"{doc['since_activation']['frames']} frames</p>")
    reasons = "".join(f"<li>{html.escape(r)}</li>" for r in doc["reasons"])
    body = f"<ul>{reasons}</ul>" if reasons else ""
    if doc["series"]:
        body += series_svg(doc["series"], win["coverage"]["levels"])
    else:
        body += ("<p class='note'>No labelled feedback yet: <code>POST /v1/feedback</code> "
                 "with frames and their ground truth.</p>")
    return head + body
