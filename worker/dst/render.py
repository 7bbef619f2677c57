"""Pictures of a deviation report: per-layer chord_dev and perimeter_err along z (the paper's Fig. 7),
and a self-contained HTML page with the summary table, the warnings and the plot."""

from __future__ import annotations

import html
import io
import os

import matplotlib

matplotlib.use("Agg")  # no display; must precede pyplot
import matplotlib.pyplot as plt  # noqa: E402

from worker.dst.forked import TaskGroup  # noqa: E402
from worker.dst.report_schema import MeshReport, Report  # noqa: E402
from worker.dst.stl_io import write_atomic  # noqa: E402

_FLOOR = 1e-7  # log axes: values below this (DST's float32 rounding) are drawn at the floor


def figure(report: Report):
    """A matplotlib figure: chord_dev (mm) and perimeter_err against z for every mesh."""
    # fixed margins (room for the tick labels, axis labels and title at this size): a constrained
    # layout made each drawing ~40% slower
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.5), sharey=True)
    fig.subplots_adjust(left=0.065, right=0.985, bottom=0.1, top=0.91, wspace=0.05)
    for m in report.meshes:
        z = [layer.z for layer in m.layers]
        style = {"linewidth": 2.2, "color": "black"} if m.kind == "dst" else {"linewidth": 1.1}
        for ax, key in zip(axes, ("chord_dev", "perimeter_err"), strict=True):
            vals = [getattr(layer, key) for layer in m.layers]
            ax.plot(
                [max(v, _FLOOR) if v is not None else float("nan") for v in vals], z, label=m.name, **style
            )
    axes[0].set_xlabel("chord_dev at the layer (mm)")
    axes[1].set_xlabel("perimeter_err at the layer (relative)")
    axes[0].set_ylabel("z above the lowest point (mm)")
    for ax in axes:
        ax.set_xscale("log")
        ax.grid(True, which="both", alpha=0.3)
    axes[1].legend(loc="best", fontsize="small")
    fig.suptitle(f"{report.input.file}: each layer's contour against the exact section")
    return fig


def write_files(
    report: Report,
    *,
    json_path: str | os.PathLike[str] | None = None,
    html_path: str | os.PathLike[str] | None = None,
    plots: tuple[str | os.PathLike[str], ...] = (),
) -> None:
    """Write the report as JSON, its HTML page and its plots (SVG or PNG by each file's extension),
    each atomically; the plot is drawn once per format (the page embeds the SVG one): a drawing
    takes ~0.3-0.5 s."""
    fmts = [_plot_format(p) for p in plots]  # a bad name fails before anything is written
    if json_path is not None:
        write_json(report, json_path)
    needed = sorted(set(fmts) | ({"svg"} if html_path is not None else set()))
    # two formats: the second drawn in a forked helper meanwhile (matplotlib holds the GIL)
    with TaskGroup(forked=len(needed) > 1, limit=1) as tasks:
        later = {fmt: tasks.submit(plot_bytes, report, fmt) for fmt in needed[1:]}
        drawn = {fmt: plot_bytes(report, fmt) for fmt in needed[:1]}
        drawn.update({fmt: task.result() for fmt, task in later.items()})
    if html_path is not None:
        write_atomic(html_path, render_html(report, drawn["svg"]).encode("utf-8"))
    for path, fmt in zip(plots, fmts, strict=True):
        write_atomic(path, drawn[fmt])


def _plot_format(path: str | os.PathLike[str]) -> str:
    fmt = os.path.splitext(os.fspath(path))[1].lower().lstrip(".")
    if fmt not in {"svg", "png"}:
        raise ValueError(f"plot format must be .svg or .png, got {os.fspath(path)!r}")
    return fmt


def plot_bytes(report: Report, fmt: str) -> bytes:
    fig = figure(report)
    buf = io.BytesIO()
    fig.savefig(buf, format=fmt, dpi=120)
    plt.close(fig)
    return buf.getvalue()


def _turn(rotation: tuple[float, float, float]) -> str:
    turns = [f"{a:g}° about {axis}" for axis, a in zip("xyz", rotation, strict=True) if a]
    return f"\nThe part is sliced turned {', then '.join(turns)}." if turns else ""


def render_html(report: Report, svg: bytes) -> str:
    """One self-contained page (no external assets) with ``svg``, the plot drawn as SVG, inline."""
    svg_text = svg.decode("utf-8")
    svg_text = svg_text[svg_text.index("<svg") :]
    e = html.escape
    rows = "\n".join(_row(m) for m in report.meshes)
    warnings = "".join(f"<li>{e(w)}</li>" for w in report.warnings) or "<li>none</li>"
    p = report.params
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<title>DST deviation report: {e(report.input.file)}</title>
<style>
body {{ font-family: system-ui, sans-serif; margin: 2em; color: #222; }}
table {{ border-collapse: collapse; }} td, th {{ padding: 0.3em 0.7em; border-bottom: 1px solid #ddd; }}
td {{ text-align: right; }} td:first-child {{ text-align: left; font-weight: 600; }}
.small {{ color: #666; font-size: 0.9em; }}
</style></head><body>
<h1>Deviation report: {e(report.input.file)}</h1>
<p>{len(report.planes)} layers, layer height {p.layer_height} mm, first layer {p.h0} mm, mode {e(p.mode)};
DST segment length {p.segment_length} mm, chord error {p.chord_error} mm.{_turn(p.rotation)}
Part height {report.input.height_mm:.4f} mm, exact volume {report.input.volume_mm3:.2f} mm³.</p>
<table>
<tr><th>mesh</th><th>triangles</th><th>STL MB</th><th>watertight</th><th>volume err</th>
<th>max vertex_dev mm</th><th>max chord_dev mm</th><th>p95 chord_dev mm</th><th>max perimeter_err</th>
<th>chord_dev vs DST</th><th>seconds</th></tr>
{rows}
</table>
<h2>Warnings</h2><ul>{warnings}</ul>
<h2>Per layer</h2>
{svg_text}
<p class="small">Reference: {e(report.reference.method)}. Distances: {e(report.reference.distances)}.
Resolution {report.reference.resolution_mm:g} mm. Report format version {e(report.version)}.</p>
</body></html>
"""


def _fmt(x: float | None, spec: str = ".3g") -> str:
    return "–" if x is None else format(x, spec)


def _row(m: MeshReport) -> str:
    s = m.summary
    ratio = (m.ratios or {}).get("max_chord_dev")
    cells = [
        html.escape(m.name),
        f"{m.triangles:,}",
        f"{m.stl_bytes / 1e6:.2f}",
        "yes" if m.watertight else "NO",
        _fmt(None if m.volume_rel_err is None else 100 * m.volume_rel_err, "+.3f") + " %",
        _fmt(s.max_vertex_dev),
        _fmt(s.max_chord_dev),
        _fmt(s.p95_chord_dev),
        _fmt(s.max_perimeter_err),
        "" if m.kind == "dst" else (_fmt(ratio, ".1f") + "×" if ratio is not None else "–"),
        _fmt(m.seconds, ".2f"),
    ]
    return "<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>"


def write_json(report: Report, path: str | os.PathLike[str]) -> None:
    write_atomic(path, report.model_dump_json(indent=1).encode("utf-8"))
