"""Measuring one mesh against the exact reference: the mesh placed as a slicer places it, cut at the
planes (a range of planes at a time, so that helpers can share the work), its per-plane metrics
(``deviation.compare``), and its report entry: the layers, the summary and the ratios to DST.

``report`` decides what is measured where; the distances are ``deviation``'s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from worker.dst.cuts import (
    MeshCut,
    crossed_planes,
    cut_mesh,
    loops_to_segments,
    offset_cut,
    select_planes,
    self_crossings,
)
from worker.dst.deviation import (
    LayerMetrics,
    SegmentSet,
    compare,
    curve_lengths,
    loop_successors,
    span_curvatures,
)
from worker.dst.meshops import edge_defects, signed_volume, unique_ints
from worker.dst.report_schema import Layer, MeshReport, Summary

# Measuring costs ~3.5 us of CPU per cut segment and ~0.8 us per reference span (fitted on the four
# default meshes of the hemisphere and the soapbox, whole and in plane ranges: within 20%, the
# DST mesh's as well)
REF_SPAN_COST = 0.23
# ... and the mesh-wide numbers (edges and volume, computed with the range that starts at plane 0)
# ~0.1-0.2 us per triangle (the hemisphere's 3,000-53,000 triangles). Left out, they unbalanced the
# helpers: the PrusaSlicer preset's, then 20 ms (two pieces' worth), came last in this process, which
# ended 35 ms after its helper.
MESH_WIDE_COST = 0.05


@dataclass
class MeshInput:
    """A mesh to measure: float coordinates as its STL holds them (mm), outward triangles."""

    name: str
    kind: Literal["dst", "baseline", "input"]
    vertices: np.ndarray
    triangles: np.ndarray
    seconds: float | None = None
    description: str = ""
    repaired: str | None = None  # a baseline made of the repaired part: where the file as read failed


@dataclass
class Measured:
    """One mesh measured at a range of planes (per-plane arrays of that length); the mesh-wide
    numbers come with the range that starts at plane 0."""

    metrics: LayerMetrics
    mesh_wide: tuple[int, int, float] | None  # open edges, non-manifold edges, volume
    side: np.ndarray  # per plane: 0, or at a flat-face plane +1 (measured above the face) / -1 (below)
    # where the cut crosses itself (``cuts.self_crossings``: plane, area, length, x, y; looked for in
    # the DST mesh only)
    pockets: tuple[tuple[int, float, float, float, float], ...] = ()


@dataclass
class BelowReference:
    """The exact sections just below the flat faces lying on planes (as plane-indexed reference
    segments; ``ExactSections.loops`` holds the ones just above)."""

    flat: np.ndarray  # (P,) bool: a flat face lies on the plane
    segments: SegmentSet
    perimeter: np.ndarray  # (P,)
    loops: np.ndarray  # (P,) loops just below the face (0 elsewhere)


def reference_segments(
    loops: list[list[np.ndarray]], corners: list[list[np.ndarray]], chord: float, n_planes: int
) -> tuple[SegmentSet, np.ndarray, np.ndarray]:
    """Exact loops per plane as the curves distances are measured to: their segment set (each span
    the curve through its ends), the perimeter and the loop count of each plane."""
    seg, plane = loops_to_segments(loops)
    curv = span_curvatures(loops, chord=chord, corners=corners)
    return (
        SegmentSet(seg, plane, curv=curv, nxt=loop_successors(loops), chord=chord),
        np.bincount(plane, weights=curve_lengths(seg, curv), minlength=n_planes),
        np.array([len(ls) for ls in loops], dtype=np.int64),
    )


def below_reference(ref, chord: float) -> BelowReference:
    n = len(ref.heights)
    segments, perimeter, loops = reference_segments(
        [ref.below_loops.get(j, []) for j in range(n)],
        [ref.below_corners.get(j, []) for j in range(n)],
        chord,
        n,
    )
    flat = np.zeros(n, dtype=bool)
    flat[ref.flat_planes] = True
    return BelowReference(flat=flat, segments=segments, perimeter=perimeter, loops=loops)


def _badness(met: LayerMetrics) -> np.ndarray:
    """Per plane, how far a cut is from a reference: chord_dev, infinite where one side is empty."""
    return np.where(np.isnan(met.chord_dev), np.inf, met.chord_dev)


def on_bed(m: MeshInput) -> tuple[np.ndarray, np.ndarray]:
    """The mesh as a slicer places it: float64 vertices with the lowest dropped to z = 0 (x, y
    unchanged), and (n, 3) triangles."""
    v = np.array(m.vertices, dtype=np.float64)
    if len(v):
        v[:, 2] -= v[:, 2].min()
    return v, np.asarray(m.triangles, dtype=np.int64).reshape(-1, 3)


class Placed:
    """A mesh as a slicer places it (``on_bed``), with the planes each triangle crosses, so that
    a range of planes is cut from its own triangles only."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, heights: np.ndarray):
        self.vertices, self.triangles = vertices, triangles
        # per triangle: the planes first .. stop - 1 cut it (``crossed_planes``)
        if len(triangles):
            self.first, self.stop = crossed_planes(vertices[:, 2][triangles], heights)
        else:
            self.first = self.stop = np.zeros(0, dtype=np.int64)

    def cut(self, heights: np.ndarray, j0: int, j1: int) -> MeshCut:
        """The mesh's cut at planes j0 .. j1 - 1 of ``heights``, from the triangles they cut."""
        sel = np.flatnonzero((self.first < j1) & (self.stop > j0))
        n = j1 - j0
        crossed = (np.clip(self.first[sel] - j0, 0, n), np.clip(self.stop[sel] - j0, 0, n))
        return cut_mesh(self.vertices, self.triangles[sel], heights[j0:j1], crossed)


def measure_planes(
    mesh: Placed,
    heights: np.ndarray,
    j0: int,
    j1: int,
    ref_set: SegmentSet,
    ref_perimeter: np.ndarray,
    below: BelowReference | None,
    n_planes: int,
    workers: int,
    crossings: bool = False,
) -> Measured:
    """Cut a placed mesh at planes j0 .. j1 - 1 and measure the cuts (pure numpy: runs in a forked
    helper). At a plane through a flat face the cut is measured against the exact outlines above
    and below the face, and keeps the better match. ``crossings``: where the cut crosses itself is
    looked for too."""
    v, tr = mesh.vertices, mesh.triangles
    cut = offset_cut(mesh.cut(heights, j0, j1), j0, n_planes)
    pockets = tuple(self_crossings(cut, points=True)) if crossings else ()
    met = compare(cut, ref_set, ref_perimeter, n_planes, workers=workers)
    side = np.zeros(n_planes, dtype=np.int8)
    if below is not None:
        flat = np.zeros(n_planes, dtype=bool)
        flat[j0:j1] = below.flat[j0:j1]
        if flat.any():
            low = compare(
                select_planes(cut, flat), below.segments, below.perimeter, n_planes, workers=workers
            )
            take = flat & (_badness(low) < _badness(met))
            side[flat] = 1
            side[take] = -1
            for k in LayerMetrics.__dataclass_fields__:
                getattr(met, k)[take] = getattr(low, k)[take]
    part = LayerMetrics(**{k: getattr(met, k)[j0:j1] for k in LayerMetrics.__dataclass_fields__})
    mesh_wide = None
    if j0 == 0:
        open_edges, nonmanifold = edge_defects(tr, len(v)) if len(tr) else (0, 0)
        mesh_wide = (open_edges, nonmanifold, signed_volume(v, tr) if len(tr) else 0.0)
    return Measured(part, mesh_wide, side[j0:j1], pockets)


def measure_pieces(
    pieces: list[tuple[Placed, int, int, bool]],
    heights: np.ndarray,
    ref_set: SegmentSet,
    ref_perimeter: np.ndarray,
    below: BelowReference | None,
    n_planes: int,
    workers: int,
) -> list[Measured]:
    """``measure_planes`` for each (mesh, j0, j1, crossings) piece, in one helper."""
    return [
        measure_planes(mesh, heights, j0, j1, ref_set, ref_perimeter, below, n_planes, workers, check)
        for mesh, j0, j1, check in pieces
    ]


def mesh_report(
    m: MeshInput,
    parts: list[Measured],
    planes_z: np.ndarray,
    loops_exact: np.ndarray,
    below: BelowReference | None,
) -> MeshReport:
    """The mesh's report from its measured plane ranges (in plane order, covering every plane);
    ``volume_rel_err`` is left to the caller, which has the exact volume."""
    met = LayerMetrics(
        **{
            k: np.concatenate([getattr(p.metrics, k) for p in parts])
            for k in LayerMetrics.__dataclass_fields__
        }
    )
    n_planes = len(planes_z)
    assert len(met.vertex_dev) == n_planes, "the plane ranges must cover every plane once"
    open_edges, nonmanifold, volume = next(p.mesh_wide for p in parts if p.mesh_wide is not None)
    side = np.concatenate([p.side for p in parts])
    if below is not None:  # the exact loops of the side each flat-face plane was measured against
        loops_exact = np.where(side < 0, below.loops, loops_exact)
    n_tri = len(np.asarray(m.triangles).reshape(-1, 3))
    layers = [
        Layer(
            index=j,
            z=float(planes_z[j]),
            vertex_dev=_num(met.vertex_dev[j]),
            chord_dev=_num(met.chord_dev[j]),
            perimeter_err=_num(met.perimeter_err[j]),
            loops=int(met.loops[j]),
            loops_exact=int(loops_exact[j]),
            open_chains=int(met.open_chains[j]),
            vertices=int(met.vertices[j]),
            flat_side=_SIDES[int(side[j])],
        )
        for j in range(n_planes)
    ]
    cut_has = met.vertices > 0
    ref_has = loops_exact > 0
    summary = Summary(
        **_stats("vertex_dev", met.vertex_dev),
        **_stats("chord_dev", met.chord_dev),
        **_stats("perimeter_err", met.perimeter_err),
        layers_missing=int((ref_has & ~cut_has).sum()),
        layers_extra=int((cut_has & ~ref_has).sum()),
        layers_loop_mismatch=int((met.loops + met.open_chains != loops_exact).sum()),
    )
    return MeshReport(
        name=m.name,
        kind=m.kind,
        description=m.description,
        triangles=n_tri,
        vertices=len(m.vertices),
        stl_bytes=84 + 50 * n_tri,
        watertight=open_edges == 0 and nonmanifold == 0 and n_tri > 0,
        open_edges=open_edges,
        nonmanifold_edges=nonmanifold,
        volume_mm3=volume,
        seconds=None if m.seconds is None else round(float(m.seconds), 4),
        summary=summary,
        layers=layers,
    )


def plane_costs(mesh: Placed, ref_per_plane: np.ndarray) -> np.ndarray:
    """Relative work of measuring a placed mesh at each plane: its cut's segments (triangles crossing
    the plane) and the reference's spans, weighed by what each costs (``REF_SPAN_COST``); plane 0
    also carries the mesh-wide numbers (``MESH_WIDE_COST`` per triangle), which the range that
    starts there computes."""
    n = len(ref_per_plane)
    crossings = np.zeros(n + 1)
    np.add.at(crossings, mesh.first, 1.0)
    np.add.at(crossings, mesh.stop, -1.0)
    cost = np.cumsum(crossings)[:n] + REF_SPAN_COST * ref_per_plane
    if n:
        cost[0] += MESH_WIDE_COST * len(mesh.triangles)
    return cost


def plane_ranges(cost: np.ndarray, chunk: float) -> list[tuple[int, int]]:
    """Consecutive plane ranges covering every plane, each of about ``chunk`` work (at least one)."""
    n = len(cost)
    parts = 1
    if np.isfinite(chunk) and chunk > 0:
        parts = max(1, min(n, round(float(cost.sum()) / chunk)))
    if parts == 1:
        return [(0, n)]
    cum = np.cumsum(cost)
    cuts = np.searchsorted(cum, cum[-1] * np.arange(1, parts) / parts)
    edges = unique_ints(np.concatenate([[0], np.clip(cuts, 1, n - 1), [n]]))
    return list(zip(edges[:-1].tolist(), edges[1:].tolist(), strict=True))


_SIDES: dict[int, Literal["above", "below"] | None] = {0: None, 1: "above", -1: "below"}


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _stats(name: str, values: np.ndarray) -> dict[str, float | None]:
    ok = values[np.isfinite(values)]
    if not len(ok):
        return {f"max_{name}": None, f"mean_{name}": None, f"p95_{name}": None}
    return {
        f"max_{name}": float(ok.max()),
        f"mean_{name}": float(ok.mean()),
        f"p95_{name}": float(np.percentile(ok, 95)),
    }


def ratios(s: Summary, dst: Summary) -> dict[str, float | None]:
    out: dict[str, float | None] = {}
    for key in (
        "max_vertex_dev",
        "mean_vertex_dev",
        "max_chord_dev",
        "mean_chord_dev",
        "p95_chord_dev",
        "max_perimeter_err",
        "mean_perimeter_err",
    ):
        a, b = getattr(s, key), getattr(dst, key)
        out[key] = a / b if a is not None and b else None
    return out
