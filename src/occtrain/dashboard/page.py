"""The dashboard as one self-contained HTML page: inline CSS, inline SVG charts, PNGs as data URIs."""

from __future__ import annotations

import base64
import re
import time
from html import escape

from occtrain.core.published import REAL_DATA, figures_for, metric_words
from occtrain.dashboard.run_view import DriveView, RunView, StageView
from occtrain.dashboard.svg import line_chart
from occtrain.formats.metrics_file import Provenance
from occtrain.metrics.closed_loop_scores import TABLE_COLUMNS
from occtrain.metrics.conventions import OCC3D, OCCWORLD, STP3, UNIAD
from occtrain.report.compare import TABLE_FILE

STATUS_COLOURS = {"done": "#2e7d32", "running": "#1565c0", "failed": "#c62828", "pending": "#757575"}
#: Metric conventions, in the order their tables appear, with what each one means.
CONVENTIONS = (
    (
        OCC3D,
        "Occ3D convention: voxels seen by the camera only; mIoU over the 17 semantic classes, IoU occupied vs free (%)",
    ),
    (
        OCCWORLD,
        "OccWorld convention: every voxel, no mask; mIoU over the 17 semantic classes, IoU occupied vs free (%)",
    ),
    (STP3, "ST-P3 convention: the value at t is the mean over all waypoints up to t"),
    (UNIAD, "UniAD convention: the value at exactly t"),
)
OTHER = "Other metrics (no convention in the name)"

CSS = """
body{font-family:"DejaVu Sans",Arial,sans-serif;margin:0;background:#f4f5f7;color:#1d1f23;font-size:14px}
header{background:#1d2733;color:#fff;padding:18px 28px}
header h1{margin:0 0 6px;font-size:22px} header .meta{color:#c9d1da;font-size:13px}
main{padding:12px 28px 40px;max-width:1240px}
section.stage{background:#fff;border-radius:8px;padding:14px 20px;margin:18px 0;box-shadow:0 1px 3px rgba(0,0,0,.12)}
h2{font-size:18px;margin:6px 0 10px} h3{font-size:15px;margin:16px 0 8px;color:#333}
table{border-collapse:collapse;margin:6px 0 10px}
th,td{padding:5px 10px;border-bottom:1px solid #e3e5e8;text-align:left;vertical-align:top}
th{background:#eef0f3;font-weight:600;white-space:nowrap} td.num{text-align:right;font-variant-numeric:tabular-nums}
.badge{display:inline-block;color:#fff;border-radius:10px;padding:1px 10px;font-size:12px;font-weight:600}
.paper{color:#6a4c00;font-size:12px} .paper b{color:#3d2c00}
.tag{background:#fff3cd;border:1px solid #e6c96b;color:#6a4c00;border-radius:4px;padding:0 5px;font-size:11px;
  white-space:nowrap}
.note{color:#555;font-size:12px;margin:2px 0 6px} .problem{color:#b00020}
.charts{display:flex;flex-wrap:wrap;gap:10px} .charts svg.chart{flex:0 0 360px}
svg.chart{background:#fff;border:1px solid #e3e5e8;border-radius:4px;font-size:11px;width:360px;height:auto}
svg .ct{text-anchor:middle;font-size:13px;font-weight:600;fill:#222} svg .xt{text-anchor:middle;fill:#444}
svg .yt{text-anchor:end;fill:#444} svg .xl,svg .yl{text-anchor:middle;fill:#222}
svg .lg{fill:#222} svg .empty{text-anchor:middle;fill:#888} svg .pa{fill:#fbfbfc}
svg .grid{stroke:#e2e4e8;stroke-width:1} svg .axis{stroke:#555;stroke-width:1}
.figs{display:flex;flex-wrap:wrap;gap:12px;align-items:flex-start} figure{margin:8px 0;max-width:100%}
figure img{max-width:100%;max-height:340px;border:1px solid #ddd} figcaption{font-size:12px;color:#444}
td.ok{color:#2e7d32;font-weight:700} td.bad{color:#c62828;font-weight:700}
table.texts{table-layout:fixed;width:100%;font-size:12px}
pre{background:#f6f8fa;padding:10px;overflow:auto;font-size:12px}
"""


def _when(t: float | None) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t)) if t else "-"


def _duration(seconds: float) -> str:
    s = int(round(seconds))
    return (
        f"{s // 3600}h {s % 3600 // 60:02d}m {s % 60:02d}s"
        if s >= 3600
        else f"{s // 60}m {s % 60:02d}s"
        if s >= 60
        else f"{seconds:.1f}s"
    )


def _num(v: float) -> str:
    if abs(v) >= 1e5:
        return f"{v:,.0f}" if v == int(v) else f"{v:.4e}"
    return f"{v:.4g}"


def _badge(status: str) -> str:
    return f'<span class="badge" style="background:{STATUS_COLOURS.get(status, "#555")}">{escape(status)}</span>'


def _summary(stage: StageView) -> str:
    e = stage.entry
    if e.status == "failed":
        return f'<span class="problem">{escape(e.error or "failed")}</span>'
    if e.status == "pending":
        return "not run yet"
    if e.status == "running":
        return f"running since {_when(e.started)} (or cut off; `occtrain run` resumes it)"
    shown = [(k, stage.metrics[k]) for k in headline(stage.metrics)[:3]]
    return escape(", ".join(f"{k} = {_num(v)}" for k, v in shown))


#: What a stage is judged by, most telling first: a stage table row leads with the first
#: of these its metrics have, then the next ones; baselines never lead.
HEADLINE = (
    "val/qa_overall",
    "val/meta_action_overall",
    "val/meta_action_acc",
    "val/forecast_occworld_mIoU_avg",
    "val/plan_direct_L2_stp3_avg",
    "val/plan_cot_L2_stp3_avg",
    "val/head_generated_meta_L2_stp3_avg",
    "val/head_gt_meta_L2_stp3_avg",
    "val/head_L2_stp3_avg",
    "val/occworld_mIoU",
    "val/occ3d_mIoU",
    "val/pixel_mIoU",
    "val/depth_absrel",
    "val/speedup",
    "val/token_acc",
)
#: Baselines shown unfolded: those of the headline measures.
BASELINE_SHOWN = re.compile(
    r"(L2_stp3_avg|qa_overall|meta_action_acc|meta_action_overall|mIoU_avg|IoU_avg|occworld_mIoU|occworld_IoU|pixel_mIoU|depth_absrel)$"
)
#: Per-horizon, per-type and count entries: in the final table, folded away.
DETAIL = re.compile(r"(_[123]s$|_by_type_|_samples|_questions$|_frames_|Bleu_[123]$|pixel_IoU_)")


def headline(metrics: dict[str, float]) -> list[str]:
    """The stage's metrics in the order a reader wants them: HEADLINE ones, then the rest of
    the model's own (no baselines, no details)."""
    first = [k for k in HEADLINE if k in metrics]
    rest = [
        k
        for k in metrics
        if k not in first
        and k != "params"
        and "baseline" not in k
        and not DETAIL.search(k)
        and (not k.startswith("val/teacher_") or BASELINE_SHOWN.search(k))  # the teacher beside the student
    ]
    return first + rest


def stage_table(run: RunView) -> str:
    rows = "".join(
        f'<tr><td><a href="#stage-{escape(s.name)}">{escape(s.name)}</a></td><td>{escape(s.entry.kind)}</td>'
        f'<td>{_badge(s.entry.status)}</td><td class="num">{s.entry.attempts}</td>'
        f'<td class="num">{_duration(s.entry.wall_time_s) if s.entry.wall_time_s else "-"}</td>'
        f"<td>{_summary(s)}</td></tr>"
        for s in run.stages
    )
    head = "".join(f"<th>{h}</th>" for h in ("stage", "kind", "status", "attempts", "wall time", "summary"))
    return f"<table><tr>{head}</tr>{rows}</table>"


def _convention(metric: str) -> str:
    words = metric_words(metric)
    return next((c for c, _ in CONVENTIONS if c in words), OTHER)


def _paper_cell(metric: str) -> str:
    """The papers' figures for ``metric`` on one line; where and under which setting each
    was published shows on hover (and in each family's ``paper.py``)."""
    figs = figures_for(metric)
    if not figs:
        return ""
    items = ", ".join(
        f'<b title="{escape(f"{f.where}; {f.setting}; {f.convention}")}">{escape(f.paper)} {_num(f.value)}</b>'
        for f in figs
    )
    return f'<div class="paper"><span class="tag">{REAL_DATA}</span> {items}</div>'


def _measured_on(provenance: Provenance | None) -> str:
    """What the final metrics were measured on, a subset called one (see ``formats.metrics_file``)."""
    if provenance is None:
        return '<p class="note">measured on: not recorded (metrics written before occtrain recorded it)</p>'
    where = f"{escape(provenance.describe())} of {escape(provenance.world_name or 'an unnamed world')}"
    style = "problem" if provenance.subset else "note"
    return f'<p class="{style}">{escape(provenance.by)}: {where}; code {escape(provenance.code_version or "-")}</p>'


def metrics_tables(metrics: dict[str, float]) -> str:
    """Final metrics grouped by the convention their names carry, the papers' figures beside
    them; per-horizon, per-type and count entries in a folded table below."""
    # Baselines beside the model on the headline measures only; the rest fold away.
    baselines = [
        k for k in metrics if "baseline" in k and not k.startswith("val/teacher_") and BASELINE_SHOWN.search(k)
    ]
    main = list(dict.fromkeys(n for n in headline(metrics) + baselines if not DETAIL.search(n)))
    details = [n for n in metrics if n not in main and n != "params"]
    out = _grouped_tables(metrics, main)
    if details:
        out += (
            f"<details><summary>{len(details)} more: per horizon, per question type, sample counts</summary>"
            f"{_grouped_tables(metrics, details)}</details>"
        )
    return out


def _grouped_tables(metrics: dict[str, float], names: list[str]) -> str:
    groups: dict[str, list[str]] = {}
    for name in names:
        groups.setdefault(_convention(name), []).append(name)
    out = []
    for key, meaning in (*CONVENTIONS, (OTHER, OTHER)):
        group = groups.get(key)
        if not group:
            continue
        rows = "".join(
            f'<tr><td>{escape(n)}</td><td class="num">{_num(metrics[n])}</td><td>{_paper_cell(n)}</td></tr>'
            for n in group
        )
        out.append(
            f"<h3>{escape(meaning if key != OTHER else OTHER)}</h3>"
            "<table><tr><th>metric</th><th>this run</th><th>published figures (papers, real nuScenes data; not this "
            f"run)</th></tr>{rows}</table>"
        )
    return "".join(out)


def _images(images: list[tuple[str, bytes]]) -> str:
    return (
        '<div class="figs">'
        + "".join(
            f'<figure><img alt="{escape(cap)}" src="data:image/png;base64,{base64.b64encode(png).decode()}">'
            f"<figcaption>{escape(cap)}</figcaption></figure>"
            for cap, png in images
        )
        + "</div>"
    )


DRIVE_COLUMNS = TABLE_COLUMNS


def _drive(drive: DriveView) -> str:
    """An ``occtrain drive``'s table (infractions per route) and the stage's episodes."""
    head = "".join(f"<th>{escape(name)}</th>" for name, _, _ in DRIVE_COLUMNS)
    rows = "".join(
        f"<tr><td>{escape(driver)}</td>"
        + "".join(f"<td>{fmt.format(scores.get(key, float('nan')))}</td>" for _, key, fmt in DRIVE_COLUMNS)
        + "</tr>"
        for driver, scores in drive.drivers.items()
    )
    conventions = "; ".join(f"{escape(k)}: {escape(v)}" for k, v in drive.conventions.items())
    figures = "".join(
        f'<figure><img alt="{escape(cap)}" src="data:image/gif;base64,{base64.b64encode(gif).decode()}">'
        f"<figcaption>{escape(cap)}</figcaption></figure>"
        for cap, gif in drive.videos
    )
    return (
        f"<h3>Closed-loop driving ({drive.routes} routes of {drive.seconds:g} s, {escape(drive.name)})</h3>"
        f"<table><tr><th>driver</th>{head}</tr>{rows}</table>"
        f'<p class="note">infractions are per route; {conventions}</p>'
        + (f'<div class="figs">{figures}</div>' if figures else "")
    )


def _texts(texts: list[dict[str, str]]) -> str:
    rows = []
    for t in texts:
        same = t["prediction"].strip().lower() == t["reference"].strip().lower()
        mark = '<td class="ok">=</td>' if same else '<td class="bad">&ne;</td>'
        rows.append(
            f"<tr><td>{escape(t['task'])}</td><td>{escape(t['prompt'])}</td><td>{escape(t['prediction'])}</td>"
            f"{mark}<td>{escape(t['reference'])}</td></tr>"
        )
    return (
        '<table class="texts"><colgroup><col style="width:5%"><col style="width:27%"><col style="width:36%">'
        '<col style="width:3%"><col style="width:29%"></colgroup>'
        "<tr><th>task</th><th>prompt</th><th>prediction</th><th></th><th>reference</th></tr>"
        + "".join(rows)
        + "</table>"
    )


def stage_section(stage: StageView) -> str:
    e = stage.entry
    parts = [
        f'<section class="stage" id="stage-{escape(stage.name)}"><h2>{escape(stage.name)} '
        f'<span class="note">({escape(e.kind)})</span> {_badge(e.status)}</h2>',
        f'<div class="note">attempts {e.attempts}; started {_when(e.started)}; ended {_when(e.ended)}; '
        f"wall time {_duration(e.wall_time_s) if e.attempts else '-'}; config {escape(e.config_hash or '-')}; code "
        f"{escape(e.code_version or '-')}</div>",
    ]
    if e.status == "failed":
        parts.append(f'<p class="problem">failed: {escape(e.error or "no error recorded")}</p>')
    parts.extend(f'<p class="problem">{escape(p)}</p>' for p in stage.problems)
    if stage.charts:
        parts.append('<h3>Curves</h3><div class="charts">')
        parts.extend(line_chart(c.series, c.title, "step", c.ylabel) for c in stage.charts)
        parts.append("</div>")
    elif e.status != "pending":
        parts.append('<p class="note">no training log (logs/csv/metrics.csv) for this stage.</p>')
    if stage.metrics:
        parts.append("<h3>Final metrics</h3>" + _measured_on(stage.provenance) + metrics_tables(stage.metrics))
    elif e.status == "done":
        parts.append('<p class="note">the stage recorded no final metrics.</p>')
    parts.extend(_drive(drive) for drive in stage.drives)
    if stage.images:
        parts.append("<h3>Bird's-eye views (validation)</h3>" + _images(stage.images))
    if stage.texts:
        parts.append("<h3>Generated text vs reference (validation)</h3>" + _texts(stage.texts))
    if e.status == "pending":
        parts.append('<p class="note">pending: this stage has not run yet.</p>')
    parts.append("</section>")
    return "".join(parts)


def comparison_section(run: RunView) -> str:
    """The recipe's comparison table (``table.md``, written once every stage is done), as written."""
    path = run.run_dir / TABLE_FILE
    if not path.is_file():
        return ""
    text = path.read_text(errors="replace")
    return f'<section class="stage"><h2>Comparison with the paper</h2><pre>{escape(text)}</pre></section>'


DATA_CHART_CAPTION = "class shares of the occupied voxels, beside Occ3D-nuScenes train"


def data_section(run: RunView) -> str:
    """The run's dataset beside Occ3D-nuScenes: the figures with their targets and the
    class-share chart (what ``occtrain data stats`` prints)."""
    from occtrain.data.stats import rows

    data = run.data
    if data is None:
        return ""
    if data.stats is None:
        return f'<section class="stage"><h2>Data</h2><p class="problem">{escape(data.problem)}</p></section>'
    st = data.stats
    world = f", synthetic world {st.world}" if st.world else ""
    body = "".join(
        f'<tr><td>{escape(label)}</td><td class="num">{escape(ours)}</td><td class="num">{escape(ref)}</td>'
        f'<td class="num">{escape(target)}</td><td '
        f'class="{"ok" if met == "yes" else "bad" if met == "no" else ""}">{met}</td></tr>'
        for label, ours, ref, target, met in rows(st)
    )
    table = (
        "<table><tr><th>statistic</th><th>this dataset</th><th>Occ3D-nuScenes (one "
        "frame)</th><th>target</th><th>met</th></tr>"
        f"{body}</table>"
    )
    return (
        f'<section class="stage"><h2>Data: {escape(data.root)}{escape(world)}</h2>'
        f'<p class="note">{st.frames} {escape(st.split)} frames (means over frames); '
        "<code>occtrain data stats</code> counts every frame.</p>"
        f"{table}{_images([(DATA_CHART_CAPTION, data.chart)])}</section>"
    )


def render_page(run: RunView, generated: float | None = None) -> str:
    """The whole page as one HTML string."""
    versions = sorted({s.entry.code_version for s in run.stages if s.entry.code_version})
    pipeline = (
        '<section class="stage"><details><summary>pipeline.yaml</summary>'
        f"<pre>{escape(run.pipeline_yaml)}</pre></details></section>"
        if run.pipeline_yaml
        else ""
    )
    return (
        '<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
        f"<title>occtrain run {escape(run.name)}</title><style>{CSS}</style></head><body>"
        f'<header><h1>occtrain run: {escape(run.name)}</h1><div class="meta">{escape(str(run.run_dir))} &middot; '
        f"manifest updated {_when(run.updated)} &middot; page written {_when(generated or time.time())} &middot; "
        f"code {escape(', '.join(versions) or '-')}</div></header><main>"
        f'<section class="stage"><h2>Stages</h2>{stage_table(run)}'
        f'<p class="note">Figures tagged <span class="tag">{REAL_DATA}</span> are the papers\' published numbers on '
        "real "
        "nuScenes / Occ3D-nuScenes data with full-size models, shown for orientation; this run trains on the data "
        "in pipeline.yaml.</p></section>"
        + comparison_section(run)
        + data_section(run)
        + "".join(stage_section(s) for s in run.stages)
        + pipeline
        + "</main></body></html>\n"
    )
