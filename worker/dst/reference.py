"""The exact sections a deviation report measures against.

The reference section at a plane is a dense polyline through points that lie exactly on the B-rep
(Newton on the face surfaces to ``LEVEL_TOL_MM`` in z, Brent roots on the edge curves at corners),
sampled until every span's midpoint is within ``chord`` of its chord: distances measured to it are
within ``chord`` of the distances to the exact curve. It is computed by the same batched surface
evaluation as the DST rings but from its own, finer topology mesh, so a section loop that the DST
build's coarser topology missed still shows up here. ``occt_sections`` computes the same thing with
``BRepAlgoAPI_Section`` (approximation on), slowly; the tests check that both agree.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from OCP.BRepAdaptor import BRepAdaptor_Curve
from OCP.BRepAlgoAPI import BRepAlgoAPI_Section
from OCP.BRepTools import BRepTools
from OCP.GCPnts import GCPnts_QuasiUniformDeflection
from OCP.gp import gp_Dir, gp_Pln, gp_Pnt
from OCP.TopAbs import TopAbs_EDGE
from OCP.TopExp import TopExp_Explorer
from OCP.TopoDS import TopoDS

from worker.dst import constants as C
from worker.dst.lowest import snap_extremes, snap_local_extremes
from worker.dst.pipeline import bbox_diagonal
from worker.dst.sampling import RingSampler, VertexPool
from worker.dst.sections import cut_topology
from worker.dst.step_io import LoadedPart
from worker.dst.topomesh import build_topomesh

# The exact section of a plane through a flat face is taken just above the plane: twice the larger of
# the on-plane snapping tolerance and the plane's float32 half-step (so the face is no longer "on" the
# lifted plane). A surface standing on the face moves by the lift times its slope's cotangent there.
FLAT_FACE_LIFT_FACTOR = 2.0


@dataclass
class ExactSections:
    """Exact sections of a part at heights measured from its exact lowest point.

    heights : (P,) float64   plane heights above the lowest point, mm
    loops : per plane, a list of (k, 2) float64 closed polylines in (x, y), mm (first point not repeated)
    corners : per plane and loop, (k,) bool: the section changes face or meets a B-rep edge there
    zmin, zmax : the part's exact lowest and highest z in its own coordinates, mm
    chord : largest distance between the exact curve and the polylines, mm
    method : how the points were computed (for the report)
    """

    heights: np.ndarray
    loops: list[list[np.ndarray]]
    corners: list[list[np.ndarray]]
    zmin: float
    zmax: float
    chord: float
    method: str
    flat_planes: list[int]

    def perimeters(self) -> np.ndarray:
        return np.array([sum(closed_length(p) for p in ls) for ls in self.loops])


def exact_sections(
    part: LoadedPart,
    heights: np.ndarray | Callable[[float], np.ndarray],
    *,
    chord: float,
    segment_length: float,
    deflection: float,
) -> ExactSections:
    """Dense exact sections of ``part`` at ``heights`` above its exact lowest point.

    ``heights`` may be a function of the part's exact height (highest minus lowest point).
    """
    diag, _ = bbox_diagonal(part)  # merge tolerance relative to the whole part, as in the DST build
    meshes = [_topomesh(s, deflection, diag) for s in part.solids]
    zmin, zmax = snap_extremes(meshes)
    if callable(heights):
        heights = heights(zmax - zmin)
    world = zmin + np.asarray(heights, dtype=np.float64)
    for mesh in meshes:
        snap_local_extremes(mesh, world)
    loops: list[list[np.ndarray]] = [[] for _ in range(len(world))]
    corners: list[list[np.ndarray]] = [[] for _ in range(len(world))]
    # as in the DST build: a node within half a float32 step of a plane is on it (what a slicer sees)
    noise = 0.5 * np.spacing(np.abs(np.asarray(heights, dtype=np.float32))).astype(np.float64)
    topos, flat = [], set()
    for mesh in meshes:
        topo = cut_topology(mesh, world, on_plane_tol=C.ON_PLANE_TOL_MM, noise_tol=noise)
        if topo.flat_planes:
            # A plane through a flat face of this solid: measure the solid's section just above it, as
            # a mesh cut is measured (a vertex on a plane counts as below it), i.e. the outline of what
            # stands on the face. Other solids keep the plane where it is.
            flat.update(topo.flat_planes)
            lifted = world.copy()
            j = np.asarray(topo.flat_planes)
            lifted[j] += FLAT_FACE_LIFT_FACTOR * np.maximum(C.ON_PLANE_TOL_MM, noise[j])
            topo = cut_topology(mesh, lifted, on_plane_tol=C.ON_PLANE_TOL_MM, noise_tol=noise)
        topos.append(topo)
    for mesh, topo in zip(meshes, topos, strict=True):
        pool = VertexPool()
        sampler = RingSampler(mesh, topo, pool, segment_length=segment_length, chord_error=chord)
        annulus = topo.comp_is_annulus
        free = annulus[topo.loop_below] & annulus[topo.loop_above]
        rings = sampler.free_loops(np.flatnonzero(free).tolist())
        for li in np.flatnonzero(~free).tolist():
            rings[li] = sampler.pinned_loop(li)
        xyz = pool.xyz
        for li, ids in rings.items():
            j = int(topo.loops[li][0])
            loops[j].append(xyz[ids, :2].copy())
            corners[j].append(np.array([v in sampler.corner_vids for v in ids], dtype=bool))
    return ExactSections(
        heights=np.asarray(heights, dtype=np.float64),
        loops=loops,
        corners=corners,
        zmin=zmin,
        zmax=zmax,
        chord=chord,
        flat_planes=sorted(flat),
        method=(
            "points solved exactly on the B-rep faces and edges (Newton / Brent, |z - plane| < "
            f"{C.LEVEL_TOL_MM:g} mm) and joined into closed polylines, sampled until each span's midpoint "
            f"lies within {chord:g} mm of its chord"
        ),
    )


def occt_sections(
    part: LoadedPart, heights: np.ndarray, *, zmin: float, deflection: float
) -> list[np.ndarray]:
    """Points on ``BRepAlgoAPI_Section`` of the part with each plane (approximation on), sampled within
    ``deflection``: an independent, slow check of :func:`exact_sections`. One (k, 2) array per plane."""
    out = []
    for h in np.asarray(heights, dtype=np.float64):
        plane = gp_Pln(gp_Pnt(0.0, 0.0, zmin + float(h)), gp_Dir(0.0, 0.0, 1.0))
        section = BRepAlgoAPI_Section(part.compound, plane, False)
        section.Approximation(True)
        section.ComputePCurveOn1(True)
        section.Build()
        pts = []
        exp = TopExp_Explorer(section.Shape(), TopAbs_EDGE)
        while exp.More():
            curve = BRepAdaptor_Curve(TopoDS.Edge(exp.Current()))
            sampler = GCPnts_QuasiUniformDeflection(curve, deflection)
            if sampler.IsDone():
                pts.extend(sampler.Value(i).Coord()[:2] for i in range(1, sampler.NbPoints() + 1))
            exp.Next()
        out.append(np.asarray(pts, dtype=np.float64).reshape(-1, 2))
    return out


def _topomesh(solid, deflection: float, diag: float):
    BRepTools.Clean_s(solid)
    return build_topomesh(
        solid, deflection=deflection, angular=C.TOPO_ANGULAR_RAD, merge_tol=C.MERGE_TOL_REL * diag
    )


def closed_length(p: np.ndarray) -> float:
    """Length of a closed polyline (k, 2), its last point joined to its first."""
    return float(np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1).sum())
