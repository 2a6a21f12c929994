"""Hand-written SVG drawings in a 2-D profile's image plane (no matplotlib): the calibration
over the box centre as two heat maps (raw and calibrated), and one held-out image drawn as a
canvas of its own size with its boxes.

Inputs are the `position` and `sample` entries of a 2-D fit's held-out report
(`calibrators.boxes2d`'s `_report_scores`, `_report_sample`).
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from typing import Any

from app.dashboard.intervals import MIN_TPS, too_small

#: Colours: true boxes, true and false positives, the 90 % region band, grey for too few.
TRUTH, TP, FP, BAND, GREY = "#2ca02c", "#1f77b4", "#e6550d", "#1f77b4", "#9aa3ad"
#: Width (px) of one heat map and of the image canvas on screen; the labels' size (px).
PANEL_PX, IMAGE_PX, FONT_PX = 300.0, 760.0, 12.0


def _e(value: Any) -> str:
    return html.escape(str(value))


def _heat(value: float, vmax: float) -> str:
    """White at 0 to deep red at `vmax` (and beyond)."""
    t = min(max(value / vmax, 0.0), 1.0)
    r, g, b = (round(255 + (c - 255) * t) for c in (0xc6, 0x28, 0x28))
    return f"#{r:02x}{g:02x}{b:02x}"


def position_heatmap(position: dict[str, Any], aspect: float) -> str:
    """Two heat maps (raw, calibrated) of the cells' D-ECE over the box centre, each a frame
    of the image's `aspect` (width / height), cells with fewer than `MIN_TPS` detections
    grey; each cell `<rect class="cell" data-part data-row data-col data-value>`."""
    count = position["count"]
    rows, cols = len(count), len(count[0])
    w = PANEL_PX
    h = w / aspect if aspect > 0 else w * 0.75
    parts = (("raw", "d_ece_raw"), ("calibrated", "d_ece_calibrated"))
    seen = [v for _, key in parts for r, line in enumerate(position[key])
            for c, v in enumerate(line) if v is not None and not too_small(count[r][c])]
    vmax = max(0.05, math.ceil(max(seen, default=0.0) / 0.05) * 0.05)
    top, gap, left = 22.0, 28.0, 4.0
    out = []
    for k, (part, key) in enumerate(parts):
        x0 = left + k * (w + gap)
        out.append(f'<text x="{x0 + w / 2:.1f}" y="14" text-anchor="middle" '
                   f'font-weight="600">{part} scores</text>')
        for r in range(rows):
            for c in range(cols):
                out.append(_cell(position, key, part, r, c, x0 + c * w / cols,
                                 top + r * h / rows, w / cols, h / rows, vmax))
        out.append(f'<rect x="{x0}" y="{top}" width="{w}" height="{h:.1f}" fill="none" '
                   'stroke="#555" stroke-width="1"/>')
    legend_x = left + 2 * w + gap + 16
    steps = 40
    for i in range(steps):
        y = top + h * (1 - (i + 1) / steps)
        out.append(f'<rect x="{legend_x}" y="{y:.1f}" width="12" height="{h / steps + 0.5:.1f}" '
                   f'fill="{_heat(vmax * (i + 0.5) / steps, vmax)}"/>')
    out.append(f'<text x="{legend_x + 16}" y="{top + 8}" font-size="10">{vmax:.2f}</text>'
               f'<text x="{legend_x + 16}" y="{top + h:.1f}" font-size="10">0</text>'
               f'<text x="{legend_x + 6}" y="{top + h + 16:.1f}" font-size="10" '
               'text-anchor="middle">D-ECE</text>')
    width, height = legend_x + 44, top + h + 24
    return (f'<svg class="plot" role="img" aria-label="Calibration over the image position" '
            f'xmlns="http://www.w3.org/2000/svg" width="{width:.0f}" height="{height:.0f}" '
            f'viewBox="0 0 {width:.0f} {height:.0f}" font-family="system-ui,sans-serif" '
            f'font-size="12">' + "".join(out) + "</svg>")


def _cell(position: dict[str, Any], key: str, part: str, r: int, c: int, x: float, y: float,
          w: float, h: float, vmax: float) -> str:
    """One heat-map cell: its D-ECE (colour and figure), its detections, and a tooltip."""
    n = position["count"][r][c]
    value = position[key][r][c]
    edges = position["edges"]
    small = too_small(n)
    fill = "#f3f4f6" if value is None or small else _heat(value, vmax)
    ink = GREY if value is None or small else ("#fff" if value > 0.6 * vmax else "#222")
    conf = position[f"confidence_{part}"][r][c]
    tip = (f"cx {edges[c]:.1f}–{edges[c + 1]:.1f}, cy {edges[r]:.1f}–{edges[r + 1]:.1f}: "
           f"{n} detections, {position['true_positives'][r][c]} TPs"
           + ("" if value is None else f", precision {position['precision'][r][c]:.2f}, "
              f"mean {part} confidence {conf:.2f}, D-ECE {value:.3f}")
           + (f" (fewer than {MIN_TPS}: too few to judge)" if small and n else ""))
    label = "—" if value is None else f"{value:.2f}"
    cx, cy = x + w / 2, y + h / 2
    return (f'<g><title>{_e(tip)}</title><rect class="cell" data-part="{part}" data-row="{r}" '
            f'data-col="{c}" data-value="{"" if value is None else value}" x="{x:.1f}" '
            f'y="{y:.1f}" width="{w:.1f}" height="{h:.1f}" fill="{fill}" stroke="#fff" '
            f'stroke-width="1"/><text x="{cx:.1f}" y="{cy + 1:.1f}" text-anchor="middle" '
            f'fill="{ink}" font-size="12">{label}</text><text x="{cx:.1f}" y="{cy + 13:.1f}" '
            f'text-anchor="middle" fill="{ink}" font-size="9">n {n}</text></g>')


def sample_canvas(sample: dict[str, Any]) -> str:
    """The held-out image `sample` as a canvas of its size (viewBox in image pixels): its
    ground truth (green; crowd or ignored dashed grey), each detection's region band between
    its inner and outer box at the sample's level, the detected boxes (true positives blue,
    false positives orange) labelled with category and calibrated score, no two labels
    overlapping; `<g class="det">` per detection, `<text class="label">` per label."""
    width, height = float(sample["width"]), float(sample["height"])
    px = IMAGE_PX
    unit = width / px                     # image pixels per screen pixel
    font, line = FONT_PX * unit, 1.6 * unit
    out = [f'<rect class="frame" x="0" y="0" width="{width:g}" height="{height:g}" '
           f'fill="#eef1f4" stroke="#9aa3ad" stroke-width="{line:.2f}"/>']
    for t in sample["truth"]:
        dash = f' stroke-dasharray="{4 * unit:.1f}"' if t["ignored"] else ""
        color = GREY if t["ignored"] else TRUTH
        out.append(f'<rect class="truth" {_xywh(t["bbox"])} fill="none" stroke="{color}" '
                   f'stroke-width="{2 * line:.2f}"{dash}><title>{_e(t["category"])} (ground '
                   f'truth{", ignored" if t["ignored"] else ""})</title></rect>')
    placed: list[tuple[float, float, float, float]] = []
    labels = []
    for i, d in enumerate(sample["detections"]):
        color = TP if d["true_positive"] else FP
        band = ""
        if d["outer"] is not None:
            path = _rect_path(d["outer"]) + ("" if d["inner"] is None
                                              else _rect_path(d["inner"]))
            band = (f'<path class="band" d="{path}" fill="{BAND}" fill-opacity="0.13" '
                    f'fill-rule="evenodd" stroke="{BAND}" stroke-opacity="0.5" '
                    f'stroke-width="{0.8 * line:.2f}" stroke-dasharray="{3 * unit:.1f}"/>')
        tip = (f"{d['category']}: score {d['score_raw']:.3f} raw, {d['score']:.3f} calibrated, "
               f"{'true' if d['true_positive'] else 'false'} positive")
        out.append(f'<g class="det" id="det-{i}"><title>{_e(tip)}</title>{band}<rect '
                   f'{_xywh(d["bbox"])} fill="none" stroke="{color}" '
                   f'stroke-width="{1.5 * line:.2f}"/></g>')
        text = f"{d['category']} {d['score']:.2f}"
        x, y = _place(d["bbox"], text, font, width, height, placed)
        labels.append(f'<text class="label" id="label-{i}" x="{x:.1f}" y="{y:.1f}" '
                      f'fill="{color}" font-size="{font:.1f}" font-weight="600" stroke="#fff" '
                      f'stroke-width="{3 * unit:.1f}" paint-order="stroke">{_e(text)}</text>')
    return (f'<svg class="plot image2d" role="img" aria-label="Held-out image '
            f'{_e(sample["image_id"])}" xmlns="http://www.w3.org/2000/svg" '
            f'width="{px:.0f}" height="{px * height / width:.0f}" '
            f'viewBox="0 0 {width:g} {height:g}" font-family="system-ui,sans-serif">'
            + "".join(out + labels) + "</svg>")


def _xywh(box: Sequence[float]) -> str:
    x, y, w, h = box
    return f'x="{x:.1f}" y="{y:.1f}" width="{w:.1f}" height="{h:.1f}"'


def _rect_path(box: Sequence[float]) -> str:
    x, y, w, h = box
    return f"M{x:.1f},{y:.1f}h{w:.1f}v{h:.1f}h{-w:.1f}Z"


def _place(box: Sequence[float], text: str, font: float, width: float, height: float,
           placed: list[tuple[float, float, float, float]]) -> tuple[float, float]:
    """Baseline `(x, y)` of a label of `text` near `box`: above it, inside its top, below it,
    then further up or down, the first place overlapping no label in `placed` (which gains
    this one's rectangle)."""
    x, y, w, h = box
    tw, th = 0.6 * font * len(text), 1.15 * font
    tops = [y - th - 1, y + 1, y + h + 1]
    tops += [t for k in range(1, 12) for t in (y - th - 1 - k * th, y + h + 1 + k * th)]
    left = min(max(x, 0.0), max(width - tw, 0.0))
    for top in tops:
        top = min(max(top, 0.0), height - th)
        rect = (left, top, tw, th)
        if not any(_overlap(rect, p) for p in placed):
            break
    placed.append(rect)
    return left, top + 0.85 * th


def _overlap(a: tuple[float, ...], b: tuple[float, ...]) -> bool:
    return a[0] < b[0] + b[2] and b[0] < a[0] + a[2] and a[1] < b[1] + b[3] and b[1] < a[1] + a[3]
