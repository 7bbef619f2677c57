"""Benchmark: DST against OCCT's conventional mesh at PrusaSlicer's import setting, same run.

Each measurement runs in a fresh spawned process, ``--repeat`` rounds per part (conventional, DST
with its report, job, in turn: a slow spell of a shared machine hits a whole round), and the tables
show medians; a ratio is the median of the rounds' own ratios. Seconds are the wall time of the
work (STEP read included for both), not of the process start-up; memory ("MB") is the peak resident
memory of the work above what the process held after its imports (Linux: the peak is reset after
the imports), "peak MB" the process's whole peak, imports (OCCT, scipy: ~460 MB) included. Ratios are DST /
conventional. The report's helper processes (forked: they share the parent's pages) are shown by
their largest peak resident size. A last table shows memory against the plane count.

Targets (issue 2): the B-spline hemisphere R = 20 mm at h = 0.2 mm under 1 s; ``ec_soapbox-A.stp`` at
h = 0.2 mm within 3x the conventional mesh's time; memory growing with the part, not planes squared.
Target (issue 3): the deviation report with the three default baselines within 3x the DST build time
(second table: the report's seconds, of which the exact reference and building the baselines; and
the job's, DST and report together as ``slice_and_report`` runs them, the baselines and the exact
reference started before the DST build, in two helpers at a lower priority). The report's CPU seconds (its helper processes included) against the DST
build's show its work independently of the machine's speed: on c cores the report cannot take less
than CPU / c seconds, the "floor" column.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import queue
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
CORPUS = ROOT.parent / "shared" / "corpus"


def _dst(path: str, layer: float, q, with_report: bool = True) -> None:
    from worker.dst.baselines import DEFAULT_BASELINES
    from worker.dst.params import SliceParams
    from worker.dst.pipeline import slice_step
    from worker.dst.report import build_report

    params = SliceParams(layer_height=layer)
    base = _reset_peak()
    cpu, t = _cpu_s(), time.perf_counter()
    mesh = slice_step(path, params)
    sec = time.perf_counter() - t
    out = {
        "seconds": sec,
        "cpu_s": _cpu_s() - cpu,
        "triangles": len(mesh.triangles),
        "planes": len(mesh.planes),
        "rss_mb": _rss_mb(),
        "work_mb": _peak_mb() - base,
        "stages": mesh.stats["timings_s"],
    }
    if with_report:
        base = _reset_peak()
        cpu, t = _cpu_s(), time.perf_counter()
        report = build_report(mesh.part, params, file_name=path, dst=mesh, baselines=DEFAULT_BASELINES)
        out.update(
            report_seconds=time.perf_counter() - t,
            report_cpu_s=_cpu_s() - cpu,
            reference_seconds=report.reference.seconds,
            baseline_seconds=sum(m.seconds or 0.0 for m in report.meshes if m.kind == "baseline"),
            slowest_baseline_seconds=max(
                (m.seconds or 0.0 for m in report.meshes if m.kind == "baseline"), default=0.0
            ),
            report_work_mb=_peak_mb() - base,
            helper_mb=resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0,
        )
    q.put(out)


def _job(path: str, layer: float, q) -> None:
    """DST and its report as a job runs them (``slice_and_report``: the baselines and the exact
    reference start before the DST build, in two helper processes)."""
    from worker.dst.baselines import DEFAULT_BASELINES
    from worker.dst.params import SliceParams
    from worker.dst.report import slice_and_report

    params = SliceParams(layer_height=layer)
    t = time.perf_counter()
    mesh, _ = slice_and_report(path, params, baselines=DEFAULT_BASELINES)
    q.put({"seconds": time.perf_counter() - t, "dst_seconds": mesh.stats["timings_s"]["total"]})


def _conventional(path: str, layer: float, q) -> None:
    from OCP.BRepMesh import BRepMesh_IncrementalMesh

    from worker.dst.step_io import read_step

    base = _reset_peak()
    t = time.perf_counter()
    part = read_step(path)
    comp = part.compound
    BRepMesh_IncrementalMesh(comp, 0.005, False, 1.0, True)  # PrusaSlicer 2.5 STEP import setting
    sec = time.perf_counter() - t
    work = _peak_mb() - base
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
    q.put({"seconds": sec, "triangles": n, "rss_mb": _rss_mb(), "work_mb": work})


def _cpu_s() -> float:
    """CPU seconds (user + system) of this process and of its children that have ended."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _rss_mb() -> float:
    """Peak resident memory of this process so far (imports included), MB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _status_mb(key: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    raise KeyError(key)


def _reset_peak() -> float:
    """Linux: restart the peak-RSS count here (after the imports); return the resident MB now."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    return _status_mb("VmRSS")


def _peak_mb() -> float:
    return _status_mb("VmHWM")


def measure(fn, path: str, layer: float, *extra) -> dict:
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=fn, args=(path, layer, q, *extra))
    p.start()
    deadline = time.monotonic() + 3600
    out = None
    while out is None:  # a measurement that dies (its traceback on stderr) ends the run, not hangs it
        alive = p.is_alive() and time.monotonic() < deadline
        try:
            out = q.get(timeout=1.0 if alive else 5.0)  # (a result sent just before the end)
        except queue.Empty:
            if not alive:
                p.kill()
                break
    if out is None:
        raise SystemExit(f"{fn.__name__} on {path} ended without a result (exit code {p.exitcode})")
    p.join()
    return out


def hemisphere_step(tmp: Path) -> Path:
    from tests.conftest import build_part, write_step

    return write_step(build_part("hemisphere", radius=20.0), tmp / "hemisphere_R20_bspline.step")


def _median(values) -> float:
    return float(statistics.median(values))


def main() -> None:
    from worker.dst.forked import usable_cpus

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layer-height", type=float, default=0.2)
    ap.add_argument("--parts", nargs="*", help="extra STEP files to measure")
    ap.add_argument(
        "--repeat",
        type=int,
        default=3,
        help="rounds per part (each round: conventional, DST + report, job, in fresh processes); "
        "the tables show medians, ratios as the median of each round's ratio",
    )
    ap.add_argument(
        "--no-scaling", dest="scaling", action="store_false", help="skip the memory-against-planes table"
    )
    ap.add_argument(
        "--only", nargs="*", metavar="WORD", help="measure only the parts whose name holds one of these words"
    )
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp())
    parts = [("hemisphere R20 (B-spline)", hemisphere_step(tmp))]
    for rel in ("freeform/ec_soapbox-A.stp", "mechanical/screw.step", "freeform/trj6_k1-al-214.stp"):
        if (CORPUS / rel).is_file():
            parts.append((rel, CORPUS / rel))
    parts += [(p, Path(p)) for p in args.parts or []]
    if args.only:
        parts = [(name, path) for name, path in parts if any(w in name for w in args.only)]
    cores = usable_cpus()

    head = (
        f"{'part':32} {'DST s':>7} {'conv s':>7} {'ratio':>6} {'DST tris':>9} {'conv tris':>9} "
        f"{'DST MB':>7} {'conv MB':>7} {'peak MB':>7}"
    )
    print(f"Medians of {args.repeat} rounds; seconds and memory of the work (imports excluded)")
    print("DST against OCCT's conventional mesh")
    print(head)
    print("-" * len(head))
    reports = []
    for name, path in parts:
        rounds = []
        for _ in range(args.repeat):  # interleaved: a slow spell of the machine hits all three
            conv = measure(_conventional, str(path), args.layer_height)
            dst = measure(_dst, str(path), args.layer_height)
            dst["conv"], dst["job"] = conv, measure(_job, str(path), args.layer_height)
            rounds.append(dst)
        reports.append((name, rounds))
        first = rounds[0]
        print(
            f"{name[:32]:32} {_median(r['seconds'] for r in rounds):7.2f} "
            f"{_median(r['conv']['seconds'] for r in rounds):7.2f} "
            f"{_median(r['seconds'] / r['conv']['seconds'] for r in rounds):6.2f} "
            f"{first['triangles']:9d} {first['conv']['triangles']:9d} "
            f"{_median(r['work_mb'] for r in rounds):7.0f} {_median(r['conv']['work_mb'] for r in rounds):7.0f} "
            f"{_median(r['rss_mb'] for r in rounds):7.0f}",
            flush=True,
        )
        print(f"{'':32}   DST stages (first round): {first['stages']}", flush=True)
        print(
            f"{'':32}   rounds: DST s {[round(r['seconds'], 2) for r in rounds]}, "
            f"conv s {[round(r['conv']['seconds'], 2) for r in rounds]}",
            flush=True,
        )
    print()
    print("The deviation report (3 default baselines) against the DST build it measures: run after it")
    print("(report s), and as a job runs both (job s: the baselines and the exact reference started before")
    print("the DST build, in two helpers; its added time over the DST build alone, job - DST, against DST).")
    print(f"CPU: the report's CPU seconds (helpers included) against the DST build's; on {cores} core(s)")
    print("the report cannot take less than its CPU seconds / cores (floor, against DST's wall time), nor")
    print("less than OCCT takes to make its slowest baseline (slowest/DST: a face is meshed on one thread),")
    print("which must then be measured too.")
    head = (
        f"{'part':32} {'DST s':>7} {'report s':>9} {'report/DST':>10} {'reference s':>11} "
        f"{'baselines s':>11} {'CPU/DST CPU':>11} {'floor/DST':>9} {'slowest/DST':>11} {'MB':>6} {'helper MB':>9} "
        f"{'job s':>7} {'(job-DST)/DST':>13}"
    )
    print(head)
    print("-" * len(head))
    for name, rounds in reports:
        print(
            f"{name[:32]:32} {_median(r['seconds'] for r in rounds):7.2f} "
            f"{_median(r['report_seconds'] for r in rounds):9.2f} "
            f"{_median(r['report_seconds'] / r['seconds'] for r in rounds):10.2f} "
            f"{_median(r['reference_seconds'] for r in rounds):11.2f} "
            f"{_median(r['baseline_seconds'] for r in rounds):11.2f} "
            f"{_median(r['report_cpu_s'] / r['cpu_s'] for r in rounds):11.2f} "
            f"{_median(r['report_cpu_s'] / cores / r['seconds'] for r in rounds):9.2f} "
            f"{_median(r['slowest_baseline_seconds'] / r['seconds'] for r in rounds):11.2f} "
            f"{_median(r['report_work_mb'] for r in rounds):6.0f} {_median(r['helper_mb'] for r in rounds):9.0f} "
            f"{_median(r['job']['seconds'] for r in rounds):7.2f} "
            f"{_median((r['job']['seconds'] - r['seconds']) / r['seconds'] for r in rounds):13.2f}",
            flush=True,
        )
        print(
            f"{'':32}   rounds: report/DST {[round(r['report_seconds'] / r['seconds'], 2) for r in rounds]}, "
            f"(job-DST)/DST {[round((r['job']['seconds'] - r['seconds']) / r['seconds'], 2) for r in rounds]}",
            flush=True,
        )
    if args.scaling:
        print()
        print("Memory against plane count: the hemisphere at finer layers (DST build only, one round)")
        head = f"{'layer mm':>8} {'planes':>7} {'DST s':>7} {'triangles':>10} {'MB':>6} {'MB / 100k triangles':>20}"
        print(head)
        print("-" * len(head))
        for h in (0.2, 0.1, 0.05, 0.025):
            r = measure(_dst, str(parts[0][1]), h, False)
            print(
                f"{h:8.3f} {r['planes']:7d} {r['seconds']:7.2f} {r['triangles']:10d} {r['work_mb']:6.0f} "
                f"{r['work_mb'] / r['triangles'] * 1e5:20.1f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
