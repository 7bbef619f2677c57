"""Random-turn scan: corpus parts built at random orientations, every exact point of the report's
reference at every plane measured against the DST mesh's cut there (its STL's float32 vertices,
placed as a slicer places them).

Not a benchmark of time: a search for places where a ring strays from the exact section by more than
its chord budget. Many of the build's sampling fixes came from such scans; each finding became a
corpus test at its turn and plane. A turn is printed as the three angles that
``dst slice --rotate-x/-y/-z`` (or ``SliceParams.rotate_*``) take, so a finding can be rebuilt alone.

    python benchmarks/scan_turns.py --seed 3704 --turns 2 bug24595_281390.stp boxed_sphere.step
    python benchmarks/scan_turns.py --seed 3903 --chord-error 0.005 --segment-length 0.4 r103ec.stp

The slicing settings default to the corpus tests' own for each part; given, they replace those (a
finding is then rebuilt with the same options).

Needs the shared corpus beside the checkout (``../shared/corpus``). Exits 1 if any turn is over budget
or fails to build with an unexpected error. A turn over budget only at points on needles of the
section (a spike out and back, or a cusp's thin end, under 1 um wide: ``cuts.loop_needles``) or
within the tolerance of a loose B-rep edge, each no farther from the ring than the budget and that
tolerance together (the file's faces and edges disagree by that much there:
``report_warnings.edge_tolerances``), is printed as such and not counted: the ring need not
follow what encloses no material, nor can it be held to more than the file defines. The report
names both kinds of plane.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("parts", nargs="+", help="corpus file names (e.g. boxed_sphere.step)")
    ap.add_argument("--seed", type=int, required=True, help="seed of the turns (report it with a finding)")
    ap.add_argument("--turns", type=int, default=1, help="random turns per part")
    # the slicing settings, each as ``dst slice`` takes it (default: the corpus tests' own per part)
    ap.add_argument("--layer-height", type=float)
    ap.add_argument("--first-layer-height", type=float)
    ap.add_argument("--mode", choices=["middle", "inclusive", "exclusive"])
    ap.add_argument("--segment-length", type=float)
    ap.add_argument("--chord-error", type=float)
    ap.add_argument("--target-slicer")
    args = ap.parse_args(argv)

    from tests.conftest import CORPUS

    if not CORPUS.is_dir():
        print(f"the shared STEP corpus is not beside this checkout ({CORPUS})", file=sys.stderr)
        return 2
    from tests.worker.dst.test_corpus import FILES, _exact_points_from_ring, _params
    from worker.dst.errors import DstError
    from worker.dst.params import ROTATION_FIELDS, SLICING_FIELDS, SliceParams
    from worker.dst.pipeline import slice_step
    from worker.dst.report import _exact_reference

    by_name = {p.name: p for p in FILES}
    unknown = [n for n in args.parts if n not in by_name]
    if unknown:
        print(f"not in the corpus list: {', '.join(unknown)}", file=sys.stderr)
        return 2
    settings = {
        k: getattr(args, k)
        for k in SLICING_FIELDS
        if k not in ROTATION_FIELDS and getattr(args, k) is not None
    }
    if settings:
        try:  # settings that contradict each other are refused once, not at every turn
            SliceParams.parse(**settings)
        except DstError as exc:
            print(f"settings refused ({exc.code}): {exc}", file=sys.stderr)
            return 2
        print("settings: " + ", ".join(f"{k} {v}" for k, v in settings.items()), flush=True)
    rng = np.random.default_rng(args.seed)
    failed = 0
    for name in args.parts:
        path = by_name[name]
        for _ in range(args.turns):
            turn = tuple(float(a) for a in np.round(rng.uniform(-180.0, 180.0, 3), 1))
            given = _params(path).model_dump(exclude_defaults=True) | settings
            params = SliceParams.parse(**given, **dict(zip(ROTATION_FIELDS, turn, strict=True)))
            t = time.perf_counter()
            try:
                mesh = slice_step(path, params)
            except DstError as exc:  # refused files (not a solid, resource limits) are reported, not counted
                print(f"{name} {turn} refused ({exc.code}): {str(exc)[:160]}", flush=True)
                continue
            heights = mesh.planes.section_z
            ref = _exact_reference(mesh.part, mesh.params, heights, helper=False).sections
            d, plane, pts = _exact_points_from_ring(mesh, heights, ref)
            k = int(np.argmax(d))
            over = d[k] > params.chord_error + 1e-6
            verdict = "OVER" if over else "ok"
            if over:
                needle = _on_needles(mesh, ref, d, plane, pts)
                loose = _at_loose_edges(mesh, ref, d, plane, pts)
                if (needle | loose).all():
                    over = False
                    verdict = "ok but for " + " and ".join(
                        w
                        for w, m in (
                            ("needles of the section", needle),
                            ("the file's edge tolerances", loose),
                        )
                        if m.any()
                    )
            failed += over
            print(
                f"{name} {turn} {verdict} max {d[k]:.4f} mm at z = {mesh.planes.z[plane[k]]:.4f}"
                f" (budget {params.chord_error:g}; unresolved {mesh.stats['unresolved_segments']},"
                f" gap samples {mesh.stats['gap_samples']}) {time.perf_counter() - t:.0f} s",
                flush=True,
            )
    return 1 if failed else 0


def _on_needles(mesh, ref, d: np.ndarray, plane: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Of the exact points over the chord budget, those on a needle of their plane's section
    (``cuts.loop_needles``: a spike out and back along itself, or the thin end of a cusp, under the
    reference's resolution wide, which encloses no material; the report names such planes): within
    a needle's length of its tip. ``ref``: the reference the points came from, made at every plane
    as the report makes it (a needle's tip is ill-conditioned, its legs under 1 um apart: a
    reference made at fewer planes samples it otherwise, ``bug27453`` turned (-176.6, 27.2, 113.3)
    at chord_error 0.005 mm, z = 56.9, a 7.3 um needle there and 1.6 um at that plane alone)."""
    from worker.dst.cuts import loop_needles

    over = np.flatnonzero(d > mesh.params.chord_error + 1e-6)
    out = np.zeros(len(over), dtype=bool)
    for j in np.unique(plane[over]).tolist():
        needles = [n for p in ref.loops[j] for n in loop_needles(p, ref.chord, mesh.params.chord_error)]
        for i in np.flatnonzero(plane[over] == j).tolist():
            out[i] = any(np.linalg.norm(pts[over[i]] - tip) <= length + ref.chord for length, tip in needles)
    return out


def _at_loose_edges(mesh, ref, d: np.ndarray, plane: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Of the exact points over the chord budget, those within the tolerance of a B-rep edge whose
    tolerance is at least their distance from the ring less the budget
    (``report_warnings.edge_tolerances``: the faces and the edge disagree by that much there, and
    the report names such planes)."""
    from worker.dst.report_warnings import edge_tolerances

    over = np.flatnonzero(d > mesh.params.chord_error + 1e-6)
    xyz = np.column_stack([pts[over], ref.zmin + mesh.planes.section_z[plane[over]]])
    return np.isfinite(edge_tolerances(mesh.part, xyz, d[over] - mesh.params.chord_error))


if __name__ == "__main__":
    sys.exit(main())
