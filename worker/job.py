"""One job, as run inside the sandbox process: the DST mesh and its deviation report, as files."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

Progress = Callable[[str, float], None]


def run_job(
    job_dir: Path,
    input_path: Path,
    params: dict[str, Any],
    file_name: str,
    progress: Progress,
    *,
    report_processes: int | None = None,
    on_mesh: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Build ``mesh.stl``, ``report.json``, ``report.html``, ``plot.svg`` and ``plot.png`` in ``job_dir``.

    ``report_processes``: helper processes the report may fork at once (see ``build_report``).
    ``on_mesh``: gets the mesh's summary once ``mesh.stl`` is written whole, before the report is made
    (so that a report that fails or never ends does not take the mesh with it).

    Returns a short summary for the job record. Raises the core's ``DstError`` subclasses on bad input.
    """
    from worker.dst.baselines import parse_baselines
    from worker.dst.params import SliceParams
    from worker.dst.render import write_files
    from worker.dst.report import slice_and_report

    values = dict(params)
    baselines = parse_baselines(values.pop("baselines", None))
    p = SliceParams.parse(**values)
    result: dict[str, Any] = {}

    def write_mesh(mesh) -> None:
        # written as soon as it is built, while the report's helpers work
        mesh.write_stl(job_dir / "mesh.stl")
        result.update(
            triangles=len(mesh.triangles),
            vertices=len(mesh.vertices),
            planes=len(mesh.planes),
            height_mm=float(mesh.stats["height_mm"]),
            dst_seconds=mesh.stats["timings_s"]["total"],
            warnings=list(mesh.warnings),
        )
        if on_mesh is not None:
            on_mesh(dict(result))
        progress("deviation report", 0.55)

    def stage(s: str, f: float) -> None:
        # the build 0 .. 0.55 of the job, the report 0.55 .. 0.95
        if f < 0.5:
            progress(s, 1.1 * f)
        else:
            progress(f"report: {s}", 0.55 + 0.8 * (f - 0.5))

    _, report = slice_and_report(
        input_path,
        p,
        file_name=file_name,
        baselines=baselines,
        progress=stage,
        processes=report_processes,
        on_mesh=write_mesh,
    )
    progress("plots", 0.96)
    write_files(
        report,
        json_path=job_dir / "report.json",
        html_path=job_dir / "report.html",
        plots=(job_dir / "plot.svg", job_dir / "plot.png"),
    )
    dst = report.meshes[0].summary
    result.update(
        {
            "max_vertex_dev": dst.max_vertex_dev,
            "max_chord_dev": dst.max_chord_dev,
            "warnings": report.warnings,
        }
    )
    return result
