"""Line charts as inline SVG text: axes with round-number ticks, labels, several series, a legend.

The SVG is meant to sit inside an HTML5 page, which needs no namespace declaration for it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from html import escape

#: Series colours (colour-blind friendly), cycled when a chart has more series.
PALETTE = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf")


@dataclass(frozen=True)
class Series:
    """One curve: ``label`` and points (x, y) in data units, in x order."""

    label: str
    xs: Sequence[float]
    ys: Sequence[float]


@dataclass(frozen=True)
class Frame:
    """Where the plot area sits in the SVG (pixels) and the data range it shows."""

    width: int = 560
    height: int = 280
    left: int = 64
    right: int = 16
    top: int = 30
    bottom: int = 44
    legend_row: int = 16  # height of one legend row below the x label

    def x_px(self, x: float, lo: float, hi: float) -> float:
        return self.left + (x - lo) / (hi - lo) * (self.width - self.left - self.right)

    def y_px(self, y: float, lo: float, hi: float) -> float:
        return self.height - self.bottom - (y - lo) / (hi - lo) * (self.height - self.top - self.bottom)


def nice_ticks(lo: float, hi: float, target: int = 5) -> list[float]:
    """Round tick values (1, 2 or 5 times a power of ten) spanning [lo, hi]; the ends are ticks."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"tick range [{lo}, {hi}] is not finite")
    if hi == lo:
        pad = abs(lo) * 0.1 or 1.0
        lo, hi = lo - pad, hi + pad
    raw = (hi - lo) / max(1, target)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw * (1 - 1e-9))
    first, last = math.floor(lo / step + 1e-9), math.ceil(hi / step - 1e-9)
    # 12 significant digits, not decimals: tiny ranges (a learning rate near 0) keep distinct ticks.
    return [float(f"{k * step:.12g}") for k in range(first, last + 1)]


def tick_labels(ticks: Sequence[float]) -> list[str]:
    """Labels with one format for the whole axis: fixed decimals enough for the step, or exponents."""
    top = max(abs(t) for t in ticks)
    step = abs(ticks[1] - ticks[0]) if len(ticks) > 1 else top or 1.0
    if top >= 1e5 or step < 1e-4:
        return [f"{t:.1e}" if t else "0" for t in ticks]
    decimals = max(0, -math.floor(math.log10(step) + 1e-9))
    if round(step / 10.0**-decimals, 6) % 1:  # a step of 2.5 needs one more digit
        decimals += 1
    return [f"{t:.{decimals}f}" for t in ticks]


def line_chart(
    series: Sequence[Series], title: str, xlabel: str = "step", ylabel: str = "", frame: Frame = Frame()
) -> str:
    """An ``<svg>`` element drawing each series as a ``<polyline>`` (and a dot per point)."""
    series = [s for s in series if len(s.xs)]
    legend_rows = math.ceil(len(series) / 3) if len(series) > 1 else 0
    total_h = frame.height + legend_rows * frame.legend_row
    out = [
        f'<svg class="chart" width="{frame.width}" height="{total_h}" '
        f'viewBox="0 0 {frame.width} {total_h}" role="img" aria-label="{escape(title)}">',
        f'<text x="{frame.width / 2}" y="18" class="ct">{escape(title)}</text>',
    ]
    if not series:
        out.append(f'<text x="{frame.width / 2}" y="{frame.height / 2}" class="empty">no data</text></svg>')
        return "".join(out)
    xs = [x for s in series for x in s.xs]
    ys = [y for s in series for y in s.ys]
    xt, yt = nice_ticks(min(xs), max(xs)), nice_ticks(min(ys), max(ys))
    (x0, x1), (y0, y1) = (xt[0], xt[-1]), (yt[0], yt[-1])
    plot_l, plot_r = frame.left, frame.width - frame.right
    plot_t, plot_b = frame.top, frame.height - frame.bottom
    out.append(f'<rect x="{plot_l}" y="{plot_t}" width="{plot_r - plot_l}" height="{plot_b - plot_t}" class="pa"/>')
    for v, label in zip(yt, tick_labels(yt)):
        y = frame.y_px(v, y0, y1)
        out.append(f'<line x1="{plot_l}" x2="{plot_r}" y1="{y:.1f}" y2="{y:.1f}" class="grid"/>')
        out.append(f'<text x="{plot_l - 6}" y="{y + 4:.1f}" class="yt">{label}</text>')
    for v, label in zip(xt, tick_labels(xt)):
        x = frame.x_px(v, x0, x1)
        out.append(f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{plot_b}" y2="{plot_b + 5}" class="axis"/>')
        out.append(f'<text x="{x:.1f}" y="{plot_b + 18}" class="xt">{label}</text>')
    out.append(f'<line x1="{plot_l}" x2="{plot_r}" y1="{plot_b}" y2="{plot_b}" class="axis"/>')
    out.append(f'<line x1="{plot_l}" x2="{plot_l}" y1="{plot_t}" y2="{plot_b}" class="axis"/>')
    out.append(f'<text x="{(plot_l + plot_r) / 2}" y="{plot_b + 36}" class="xl">{escape(xlabel)}</text>')
    if ylabel:
        cy = (plot_t + plot_b) / 2
        out.append(f'<text x="14" y="{cy}" transform="rotate(-90 14 {cy})" class="yl">{escape(ylabel)}</text>')
    for i, s in enumerate(series):
        colour = PALETTE[i % len(PALETTE)]
        pts = [(frame.x_px(x, x0, x1), frame.y_px(y, y0, y1)) for x, y in zip(s.xs, s.ys)]
        text = " ".join(f"{px:.1f},{py:.1f}" for px, py in pts)
        out.append(
            f'<polyline data-series="{escape(s.label)}" points="{text}" fill="none" stroke="{colour}" stroke-width="2">'
            f"<title>{escape(s.label)}</title></polyline>"
        )
        # Dots show where the samples are: sparse validation curves have only a few.
        if len(pts) <= 40:
            out.extend(f'<circle cx="{px:.1f}" cy="{py:.1f}" r="2.5" fill="{colour}"/>' for px, py in pts)
    if len(series) > 1:
        col_w = (frame.width - 2 * 12) / 3
        for i, s in enumerate(series):
            lx = 12 + (i % 3) * col_w
            ly = frame.height + (i // 3) * frame.legend_row + 4
            colour = PALETTE[i % len(PALETTE)]
            out.append(f'<rect x="{lx:.1f}" y="{ly - 9}" width="14" height="4" fill="{colour}"/>')
            out.append(f'<text x="{lx + 20:.1f}" y="{ly - 3}" class="lg">{escape(s.label)}</text>')
    out.append("</svg>")
    return "".join(out)
