"""The dashboard's calibration-health section: status, reasons and the time series of the
rolling window's ECE and served-ellipse coverage per level (hand-written inline SVG: no
plotting library on this path)."""

from __future__ import annotations

import html
from collections.abc import Sequence
from typing import Any

#: Line colours of the series: ECE, then one per level.
COLORS = ("#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b")
WIDTH, HEIGHT = 640, 250
#: Plot area inside the SVG: left, right, top, bottom edges (pixels).
LEFT, RIGHT, TOP, BOTTOM = 52, 580, 48, 208
#: The ECE axis (right) ends at the first of these that holds the series' largest value.
ECE_TOPS = (0.02, 0.05, 0.1, 0.2, 0.5, 1.0)


def _nice_ticks(top: float, n: int = 5) -> list[float]:
    """About `n` round tick values from 0 to `top` inclusive."""
    raw = top / max(n - 1, 1)
    step = min((m * 10.0 ** e for e in range(-3, 7) for m in (1, 2, 2.5, 5)
                if m * 10.0 ** e >= raw), default=raw)
    return [k * step for k in range(int(top / step + 1e-9) + 1)]


def _x(x: float, x_max: float) -> float:
    return LEFT + (RIGHT - LEFT) * x / x_max


def _y(v: float, top: float) -> float:
    return BOTTOM - (BOTTOM - TOP) * v / top


def _polyline(xs: Sequence[float], ys: Sequence[float | None], x_max: float, top: float,
              color: str, dashed: bool = False) -> str:
    points = " ".join(f"{_x(x, x_max):.1f},{_y(y, top):.1f}"
                      for x, y in zip(xs, ys, strict=True) if y is not None)
    dash = " stroke-dasharray='4 3'" if dashed else ""
    return (f"<polyline fill='none' stroke='{color}' stroke-width='1.5'{dash} "
            f"points='{points}'/>")


def _text(x: float, y: float, text: str, anchor: str = "middle", color: str = "#333",
          extra: str = "") -> str:
    return (f"<text x='{x:.1f}' y='{y:.1f}' font-size='10' fill='{color}' "
            f"text-anchor='{anchor}'{extra}>{html.escape(text)}</text>")


def _axes(x_max: float, ece_top: float) -> str:
    """Frame, grid, ticks and titles: coverage 0..1 on the left, ECE 0..`ece_top` on the
    right, feedback frames along the bottom."""
    out = [f"<rect x='{LEFT}' y='{TOP}' width='{RIGHT - LEFT}' height='{BOTTOM - TOP}' "
           "fill='none' stroke='#888'/>"]
    for v in _nice_ticks(1.0):
        y = _y(v, 1.0)
        out.append(f"<line x1='{LEFT}' y1='{y:.1f}' x2='{RIGHT}' y2='{y:.1f}' stroke='#eee'/>")
        out.append(_text(LEFT - 5, y + 3, f"{v:g}", "end", COLORS[1]))
    for v in _nice_ticks(ece_top):
        out.append(_text(RIGHT + 5, _y(v, ece_top) + 3, f"{v:g}", "start", COLORS[0]))
    for v in _nice_ticks(x_max):
        x = _x(v, x_max)
        out.append(f"<line x1='{x:.1f}' y1='{BOTTOM}' x2='{x:.1f}' y2='{BOTTOM + 4}' "
                   "stroke='#888'/>")
        out.append(_text(x, BOTTOM + 15, f"{v:g}"))
    mid = (TOP + BOTTOM) / 2
    out.append(_text((LEFT + RIGHT) / 2, BOTTOM + 32, "labelled feedback frames"))
    out.append(_text(14, mid, "coverage", color=COLORS[1],
                     extra=f" transform='rotate(-90 14 {mid:.0f})'"))
    out.append(_text(WIDTH - 12, mid, "ECE", color=COLORS[0],
                     extra=f" transform='rotate(90 {WIDTH - 12} {mid:.0f})'"))
    return "".join(out)


def _legend(entries: list[tuple[str, str, bool]]) -> str:
    """Swatches (solid or dashed line) and names above the plot, in rows of the SVG's
    width."""
    out, x, y = [], LEFT, 12
    for name, color, dashed in entries:
        width = 30 + 6 * len(name)
        if x + width > WIDTH and x > LEFT:
            x, y = LEFT, y + 15
        dash = " stroke-dasharray='4 3'" if dashed else ""
        out.append(f"<line x1='{x}' y1='{y}' x2='{x + 18}' y2='{y}' stroke='{color}' "
                   f"stroke-width='2'{dash}/>")
        out.append(_text(x + 22, y + 4, name, "start"))
        x += width
    return f"<g class='legend'>{''.join(out)}</g>"


def series_svg(series: list[dict[str, Any]], levels: Sequence[float]) -> str:
    """Window ECE (right axis, its own scale) and coverage per level (left axis, 0..1)
    against feedback frames, with the nominal levels dashed."""
    xs = [p["frames_total"] for p in series]
    x_max = max(xs[-1], 1)
    eces = [p["ece"] for p in series]
    ece_top = next((t for t in ECE_TOPS if max((e or 0.0 for e in eces), default=0.0) <= t),
                   ECE_TOPS[-1])
    lines = [_polyline(xs, eces, x_max, ece_top, COLORS[0])]
    legend = [(f"window ECE (right axis, 0–{ece_top:g})", COLORS[0], False)]
    for j, level in enumerate(levels):
        color = COLORS[1 + j % (len(COLORS) - 1)]
        lines.append(_polyline(xs, [p["coverage"][j] for p in series], x_max, 1.0, color))
        lines.append(_polyline([0, x_max], [level, level], x_max, 1.0, color, dashed=True))
        legend.append((f"coverage {level:.0%}", color, False))
    legend.append(("nominal level", "#888", True))
    return (f"<svg class='plot health-series' role='img' aria-label='Calibration health "
            f"over feedback' xmlns='http://www.w3.org/2000/svg' width='{WIDTH}' "
            f"height='{HEIGHT}' viewBox='0 0 {WIDTH} {HEIGHT}'>{_legend(legend)}"
            f"{_axes(x_max, ece_top)}" + "".join(lines) + "</svg>")


def health_section(doc: dict[str, Any]) -> str:
    """The HTML of a health document (`app.feedback.health_document`)."""
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
