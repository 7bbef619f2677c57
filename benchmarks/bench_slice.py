"""Benchmark: DST against OCCT's conventional mesh at PrusaSlicer's import setting, same run.

Each measurement runs in a fresh spawned process, so peak memory (max RSS, OCP's ~280 MB import
included) belongs to that job alone. Seconds are the wall time of the work (STEP read included for
both), not of the process start-up. Prints one table; ratios are DST / conventional.

Targets (issue 2): the B-spline hemisphere R = 20 mm at h = 0.2 mm under 1 s; ``ec_soapbox-A.stp`` at
h = 0.2 mm within 3x the conventional mesh's time; memory growing with the part, not planes squared.
Target (issue 3): the deviation report with the three default baselines within 3x the DST build time
(second table: the report's seconds, of which the exact reference and building the baselines).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import resource
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
CORPUS = ROOT.parent / "shared" / "corpus"


def _dst(path: str, layer: float, q) -> None:
    from worker.dst.baselines import DEFAULT_BASELINES
    from worker.dst.params import SliceParams
    from worker.dst.pipeline import slice_step
    from worker.dst.report import build_report

    params = SliceParams(layer_height=layer)
    t = time.perf_counter()
    mesh = slice_step(path, params)
    sec = time.perf_counter() - t
    rss = _rss_mb()
    t = time.perf_counter()
    report = build_report(mesh.part, params, file_name=path, dst=mesh, baselines=DEFAULT_BASELINES)
    report_sec = time.perf_counter() - t
    q.put(
        {
            "seconds": sec,
            "triangles": len(mesh.triangles),
            "rss_mb": rss,
            "stages": mesh.stats["timings_s"],
            "report_seconds": report_sec,
            "reference_seconds": report.reference.seconds,
            "baseline_seconds": sum(m.seconds or 0.0 for m in report.meshes if m.kind == "baseline"),
            "report_rss_mb": _rss_mb(),
        }
    )


def _conventional(path: str, layer: float, q) -> None:
    from OCP.BRepMesh import BRepMesh_IncrementalMesh

    from worker.dst.step_io import read_step

    t = time.perf_counter()
    part = read_step(path)
    comp = part.compound
    BRepMesh_IncrementalMesh(comp, 0.005, False, 1.0, True)  # PrusaSlicer 2.5 STEP import setting
    sec = time.perf_counter() - t
    from OCP.BRep import BRep_Tool
    from OCP.TopAbs import TopAbs_FACE
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopLoc import TopLoc_Location
    from OCP.TopoDS import TopoDS

    n = 0
    exp = TopExp_Explorer(comp, TopAbs_FACE)
    while exp.More():
        tri = BRep_Tool.Triangulation_s(TopoDS.Face(exp.Current()), TopLoc_Location())
        n += tri.NbTriangles() if tri is not None else 0
        exp.Next()
    q.put({"seconds": sec, "triangles": n, "rss_mb": _rss_mb()})


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def measure(fn, path: str, layer: float) -> dict:
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=fn, args=(path, layer, q))
    p.start()
    out = q.get(timeout=3600)
    p.join()
    return out


def hemisphere_step(tmp: Path) -> Path:
    from tests.conftest import build_part, write_step

    return write_step(build_part("hemisphere", radius=20.0), tmp / "hemisphere_R20_bspline.step")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layer-height", type=float, default=0.2)
    ap.add_argument("--parts", nargs="*", help="extra STEP files to measure")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp())
    parts = [("hemisphere R20 (B-spline)", hemisphere_step(tmp))]
    for rel in ("freeform/ec_soapbox-A.stp", "mechanical/screw.step", "freeform/trj6_k1-al-214.stp"):
        if (CORPUS / rel).is_file():
            parts.append((rel, CORPUS / rel))
    parts += [(p, Path(p)) for p in args.parts or []]

    head = f"{'part':32} {'DST s':>7} {'conv s':>7} {'ratio':>6} {'DST tris':>9} {'conv tris':>9} {'DST MB':>7} {'conv MB':>7}"
    print(head)
    print("-" * len(head))
    reports = []
    for name, path in parts:
        conv = measure(_conventional, str(path), args.layer_height)
        dst = measure(_dst, str(path), args.layer_height)
        reports.append((name, dst))
        print(
            f"{name[:32]:32} {dst['seconds']:7.2f} {conv['seconds']:7.2f} {dst['seconds'] / conv['seconds']:6.2f} "
            f"{dst['triangles']:9d} {conv['triangles']:9d} {dst['rss_mb']:7.0f} {conv['rss_mb']:7.0f}",
            flush=True,
        )
        print(f"{'':32}   DST stages: {dst['stages']}", flush=True)
    print()
    head = f"{'part':32} {'DST s':>7} {'report s':>9} {'report/DST':>10} {'reference s':>11} {'baselines s':>11} {'MB':>6}"
    print(head)
    print("-" * len(head))
    for name, dst in reports:
        print(
            f"{name[:32]:32} {dst['seconds']:7.2f} {dst['report_seconds']:9.2f} "
            f"{dst['report_seconds'] / dst['seconds']:10.2f} {dst['reference_seconds']:11.2f} "
            f"{dst['baseline_seconds']:11.2f} {dst['report_rss_mb']:6.0f}"
        )


if __name__ == "__main__":
    main()
