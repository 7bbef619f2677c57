"""The exact sections a deviation report measures against.

The reference section at a plane is a dense polyline through points that lie exactly on the B-rep
(Newton on the face surfaces to ``LEVEL_TOL_MM`` in z, Brent roots on the edge curves at corners),
sampled until every span's midpoint is within ``chord`` of its chord: distances measured to it are
within ``chord`` of the distances to the exact curve. It is computed by the same batched surface
evaluation as the DST rings but from its own, finer topology mesh (of the solid with its faces
with a pole divided in quarters, which BRepMesh meshes faster), so a section loop that the DST
build's coarser topology missed still shows up here. ``occt_sections`` computes the same thing with
``BRepAlgoAPI_Section`` (approximation on), slowly; the tests check that both agree.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TypeVar

import numpy as np
from OCP.BRep import BRep_Tool
from OCP.BRepAdaptor import BRepAdaptor_Curve, BRepAdaptor_Surface
from OCP.BRepAlgoAPI import BRepAlgoAPI_Section
from OCP.BRepTools import BRepTools
from OCP.collections import IndexedMap_TopoDS_Shape_TopTools_ShapeMapHasher as ShapeIndexedMap
from OCP.GCPnts import GCPnts_QuasiUniformDeflection
from OCP.gp import gp_Dir, gp_Pln, gp_Pnt
from OCP.ShapeBuild import ShapeBuild_ReShape
from OCP.ShapeUpgrade import ShapeUpgrade_ShapeDivideArea
from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE
from OCP.TopExp import TopExp, TopExp_Explorer
from OCP.TopoDS import TopoDS, TopoDS_Shape

from worker.dst import constants as C
from worker.dst.errors import TessellationError, UnmeshedFaceError
from worker.dst.exact import FaceEval
from worker.dst.forked import TaskGroup, idle_cores
from worker.dst.lowest import snap_extremes
from worker.dst.pipeline import bbox_diagonal
from worker.dst.ridges import prepare_extremes
from worker.dst.sampler_records import VertexPool
from worker.dst.sampling import RingSampler
from worker.dst.sections import cut_topology, section_pairs_per_plane
from worker.dst.step_io import LoadedPart, heal_wires
from worker.dst.topomesh import TopoMesh, build_topomesh

# Deflections (times the one asked for) tried in turn for the reference's topology mesh: BRepMesh's
# result at some deflections is not a closed manifold on some files, at others it is. The coarser
# one first (still finer than the DST build's at the report's half of it): BRepMesh's time can grow
# far faster than its triangles. Where a face is left unmeshed, the coarser ones and then the repair
# the DST build would make come before any finer one (``_reference_topomesh``): trj7_b1-ec-214
# turned (-99.8, 126.0, -162.8) as read, whose face 354 the build repairs, has a face unmeshed at
# 0.01 mm (8 s), 0.014 mm (1.6 s) and 0.02 mm, and took more than 15 minutes at 0.007 mm (stopped);
# repaired, it meshes at 0.01 mm in 2 s.
RETRY_DEFLECTIONS = (1.0, 1.4, 0.7, 2.0)

# The exact sections of a plane through a flat face are taken a small offset (mm) above and below it:
# nearly the limits of the section from either side. A surface meeting the face at a slope moves by
# this times the slope's cotangent; one tangent to it (a fillet of radius r) by sqrt(2 r offset):
# 0.0009 mm at r = 100 mm for 4e-9 mm, below the reference's resolution.
# Offsets tried in turn: a node of another face within the file's tolerance of the plane (a wall's
# vertex 0.1 um below a face it bounds) can put a crossing where a tiny offset has no exact point.
FLAT_FACE_OFFSETS_MM = (4e-9, 1e-7, 2e-6, 3e-5)
# The reference's sampling in this many shares of its planes (see ``_sample``): each share's own
# sampler costs ~2% more sampling (shorter batches) at 4 shares, ~14% at 8 (the soapbox)
SAMPLING_SHARES = 4
# A face with a pole is meshed in this many parts along u and v (``divide_pole_faces``)
POLE_FACE_SPLITS = (2, 2)
# A part of a divided face whose surface is farther than this from its face's at the same (u, v)
# does not keep the face's parameters (``_on_solid_faces``; the hemisphere's quarters: 4e-15 mm)
PART_PARAMETERS_TOL_MM = 1e-9
Pair = tuple[np.ndarray, np.ndarray]  # a closed loop (k, 2) and its corner mask (k,)
T = TypeVar("T")


@dataclass
class ExactSections:
    """Exact sections of a part at heights measured from its exact lowest point.

    heights : (P,) float64   plane heights above the lowest point, mm
    loops : per plane, a list of (k, 2) float64 closed polylines in (x, y), mm (first point not repeated)
    corners : per plane and loop, (k,) bool: the section changes face or meets a B-rep edge there
    flat_planes : planes through a flat face: there ``loops`` is the section just above the face and
        ``below_loops[j]`` (``below_corners[j]``) the one just below it
    zmin, zmax : the part's exact lowest and highest z in its own coordinates, mm
    chord : largest distance between the exact curve and the polylines, mm
    method : how the points were computed (for the report)
    unresolved : (plane, length in mm) of each segment the sampling left over ``chord`` after its
        last round (``RingSampler.keep_unresolved``): between its exact ends the reference is
        straight there
    repairs : (solid index, what was done) where OCCT could not mesh a solid as read and the
        reference is of its repair (``_reference_topomesh``)
    """

    heights: np.ndarray
    loops: list[list[np.ndarray]]
    corners: list[list[np.ndarray]]
    zmin: float
    zmax: float
    chord: float
    method: str
    flat_planes: list[int]
    below_loops: dict[int, list[np.ndarray]]
    below_corners: dict[int, list[np.ndarray]]
    unresolved: list[tuple[int, float]] = field(default_factory=list)
    repairs: list[tuple[int, str]] = field(default_factory=list)

    def perimeters(self) -> np.ndarray:
        return np.array([sum(closed_length(p) for p in ls) for ls in self.loops])


def exact_sections(
    part: LoadedPart,
    heights: np.ndarray | Callable[[float], np.ndarray],
    *,
    chord: float,
    segment_length: float,
    deflection: float,
    repair_precision: float | None = None,
    parallel: bool = True,
    helper: bool = True,
) -> ExactSections:
    """Dense exact sections of ``part`` at ``heights`` above its exact lowest point.

    ``heights`` may be a function of the part's exact height (highest minus lowest point).
    ``repair_precision``: a solid whose topology mesh leaves a face unmeshed is repaired to it as
    the DST build repairs one (its mesh's deflection), if that helps (None: never).
    ``parallel``: the topology mesh's faces on OCCT's thread pool (never in a forked process).
    ``helper``: the sampling of the upper planes in a forked helper process (see ``_sample``); the
    sections are the same either way.
    """
    diag, _ = bbox_diagonal(part)  # merge tolerance relative to the whole part, as in the DST build
    meshes, used, repairs = [], [], []
    for i, solid in enumerate(part.solids):
        mesh, d, repair = _reference_topomesh(solid, deflection, diag, parallel, repair_precision)
        meshes.append(mesh)
        used.append(d)
        if repair is not None:
            repairs.append((i, repair))
    zmin, zmax = snap_extremes(meshes)
    if callable(heights):
        heights = heights(zmax - zmin)
    world = zmin + np.asarray(heights, dtype=np.float64)
    n_planes = len(world)
    # as in the DST build: a node within half a float32 step of a plane is on it (what a slicer sees)
    noise = 0.5 * np.spacing(np.abs(np.asarray(heights, dtype=np.float32))).astype(np.float64)
    for mesh in meshes:
        prepare_extremes(mesh, world, noise)
    # per solid: (loop, corner mask) pairs at each plane, and just below its flat faces
    per_solid = [_sections_in_runs(mesh, world, noise, chord, segment_length, helper) for mesh in meshes]
    flat = sorted({j for _, below, _, _ in per_solid for j in below})
    # just below a flat face on plane j: that solid's section there, every other solid's at j
    pairs_below = {j: [p for on, below, _, _ in per_solid for p in below.get(j, on[j])] for j in flat}
    pairs = [[p for on, _, _, _ in per_solid for p in on[j]] for j in range(n_planes)]
    offsets = [off for *_, off in per_solid if off is not None]
    unresolved = [s for _, _, short, _ in per_solid for s in short]
    return ExactSections(
        heights=np.asarray(heights, dtype=np.float64),
        loops=[[lp for lp, _ in ps] for ps in pairs],
        corners=[[c for _, c in ps] for ps in pairs],
        zmin=zmin,
        zmax=zmax,
        chord=chord,
        flat_planes=flat,
        below_loops={j: [lp for lp, _ in ps] for j, ps in pairs_below.items()},
        below_corners={j: [c for _, c in ps] for j, ps in pairs_below.items()},
        unresolved=unresolved,
        repairs=repairs,
        method=(
            f"sections found on a topology mesh of deflection {_deflections(used)} mm, their "
            "points solved exactly on the B-rep faces and edges (Newton / Brent, |z - plane| < "
            f"{C.LEVEL_TOL_MM:g} mm) and joined into closed polylines, sampled until each span's midpoint "
            f"lies within {chord:g} mm of its chord"
            + (
                f"; at a plane through a flat face, the sections {max(offsets):g} mm above and below the face"
                if offsets
                else ""
            )
        ),
    )


def _sections_in_runs(
    mesh, world: np.ndarray, noise: np.ndarray, chord: float, segment_length: float, helper: bool = True
) -> tuple[list[list[Pair]], dict[int, list[Pair]], list[tuple[int, float]], float | None]:
    """``_solid_sections`` of runs of consecutive planes, each cut on its own when all of them at once
    would cross the topology mesh's triangles more than ``MAX_SECTION_PAIRS`` times (the cut's memory
    limit, which the DST build's coarser topology mesh may keep under while this finer one does not):
    the same sections, in the memory of one run's cut at a time."""
    on: list[list[Pair]] = []
    below: dict[int, list[Pair]] = {}
    unresolved: list[tuple[int, float]] = []
    offsets = []
    for j0, j1 in _plane_runs(section_pairs_per_plane(mesh, world), C.MAX_SECTION_PAIRS):
        part_on, part_below, part_unresolved, offset = _solid_sections(
            mesh, world[j0:j1], noise[j0:j1], chord, segment_length, helper
        )
        on.extend(part_on)
        below.update({j0 + j: pairs for j, pairs in part_below.items()})
        unresolved += [(j0 + j, length) for j, length in part_unresolved]
        offsets += [] if offset is None else [offset]
    return on, below, unresolved, max(offsets, default=None)


def _plane_runs(pairs: np.ndarray, limit: int) -> list[tuple[int, int]]:
    """Consecutive runs (j0, j1) of planes whose (triangle, plane) pairs add up to at most ``limit``
    each (a plane over it alone makes a run of its own, which its cut then refuses)."""
    runs, j0, total = [], 0, 0
    for j, n in enumerate(pairs.tolist()):
        if j > j0 and total + n > limit:
            runs.append((j0, j))
            j0, total = j, 0
        total += n
    return [*runs, (j0, len(pairs))]


def _solid_sections(
    mesh, world: np.ndarray, noise: np.ndarray, chord: float, segment_length: float, helper: bool = True
) -> tuple[list[list[Pair]], dict[int, list[Pair]], list[tuple[int, float]], float | None]:
    """One solid's dense sections: (loop, corner mask) pairs per plane, and per plane through a flat
    face of the solid, the pairs just below the face (the per-plane ones are then just above it);
    the segments not resolved to the chord, as (plane, length) (``_sample``); and the offset from the face
    the sections at a flat face were taken at (None without a flat face)."""
    topo = cut_topology(mesh, world, on_plane_tol=C.ON_PLANE_TOL_MM, noise_tol=noise)
    if not topo.flat_planes:
        return *_sample(
            mesh,
            topo,
            np.arange(len(world)),
            np.zeros(len(world), dtype=bool),
            [],
            chord,
            segment_length,
            helper,
        ), None
    # The solid's section at a plane through its flat face is an area: take the sections just above
    # and just below the face instead (the outlines of what stands on it and of what it caps: the two
    # slicer conventions), in one cut with the two heights in place of the plane. The nodes as the
    # first cut placed them: a flat face's nodes exactly on its plane (those off it by the file's
    # tolerance too), and every node it put on a plane exactly there, so tolerances below the offset
    # reproduce the first cut's decisions at the other planes while the moved planes miss the face.
    placed = replace(mesh, xyz=np.column_stack([mesh.xyz[:, :2], topo.z]))
    j = np.asarray(topo.flat_planes)

    def at(offset: float):
        ext = np.concatenate([world, world[j] - offset])
        ext[j] += offset
        order = np.argsort(ext, kind="stable")
        owner = np.concatenate([np.arange(len(world)), j])[order]
        lowered = np.concatenate([np.zeros(len(world), dtype=bool), np.ones(len(j), dtype=bool)])[order]
        tight = 0.25 * offset
        cut = cut_topology(placed, ext[order], on_plane_tol=tight, noise_tol=np.full(len(ext), tight))
        others_left = offset != FLAT_FACE_OFFSETS_MM[-1]
        if others_left:
            _flat_planes_resolve(placed, cut, np.isin(owner, j), chord, segment_length)
        on, below, unresolved = _sample(
            placed, cut, owner, lowered, topo.flat_planes, chord, segment_length, helper
        )
        # segments left unresolved at one offset may not be at the next, as one that fails there
        if unresolved and others_left:
            raise TessellationError(f"{len(unresolved)} unresolved segments")
        return on, below, unresolved, offset

    return _first_that_works(at, FLAT_FACE_OFFSETS_MM)


def _flat_planes_resolve(mesh, cut, flat_cut: np.ndarray, chord: float, segment_length: float) -> None:
    """Raise TessellationError where the loops of ``cut``'s planes marked in ``flat_cut`` (those just
    above and below the flat faces) cannot be sampled, or not to the chord: an offset that fails there
    fails at once, without sampling every other plane first (bug29241's reference sampled all its
    1,400 planes at three offsets that failed at one flat face or the other: 30 s of its 64). Where they
    pass, ``_sample`` samples every plane as before (these loops again, among their shares): the
    sections are those of the offset that works, as without this check."""
    ids = [li for li, (e, _) in enumerate(cut.loops) if flat_cut[int(e)]]
    if ids:
        _, unresolved = _sample_loops(mesh, cut, ids, chord, segment_length)
        if unresolved:
            raise TessellationError(f"{len(unresolved)} unresolved segments next to a flat face")


def _first_that_works(fn: Callable[[float], T], values: tuple[float, ...]) -> T:
    """``fn`` of the first of ``values`` for which it raises no TessellationError (the last one's
    error is raised)."""
    for value in values[:-1]:
        try:
            return fn(value)
        except TessellationError:
            continue  # the next value
    return fn(values[-1])


def _sample(mesh, topo, owner, lowered, flat, chord, segment_length, helper=True):
    """The dense loops of a cut, as (loop, corner mask) pairs per plane ``owner[e]`` of each cut
    plane ``e``, the ``lowered`` ones apart per flat plane; and the segments its samplers left
    unresolved (``RingSampler.keep_unresolved``), as (plane ``owner[e]``, length).

    The sampling (most of the reference's work after its topology mesh) is done in shares of the
    cut's planes (``_plane_shares``), each by a sampler of its own, one after the other; with
    ``helper``, when a core is idle between two shares (``idle_cores``: the soapbox's reference
    outlasts the report's OCCT work), half of those left go to a forked helper. Not otherwise: a
    helper that only takes turns on a busy core costs its fork and first touches of the shared
    memory (~0.14 CPU-s of the hemisphere's 2.5). The loops of one plane stay together (they may
    share nodes lying in the plane), and each share's loops are the same wherever it runs."""
    shares = _plane_shares(topo, SAMPLING_SHARES)
    sampled: dict[int, Pair] = {}
    unresolved: list[tuple[int, float]] = []
    with TaskGroup(forked=helper and len(shares) > 1, limit=1) as tasks:
        later = None
        while shares:
            if tasks.forked and later is None and len(shares) >= 2 and idle_cores() > 0:
                half = len(shares) // 2
                later = tasks.submit(_sample_shares, mesh, topo, shares[-half:], chord, segment_length)
                shares = shares[:-half]
            loops, short = _sample_loops(mesh, topo, shares.pop(0), chord, segment_length)
            sampled.update(loops)
            unresolved += short
        if later is not None:
            loops, short = later.result()
            sampled.update(loops)
            unresolved += short
    on_plane: list[list[Pair]] = [[] for _ in range(int(owner.max()) + 1 if len(owner) else 0)]
    below: dict[int, list[Pair]] = {int(k): [] for k in flat}
    for li in sorted(sampled):
        e = int(topo.loops[li][0])
        (below[int(owner[e])] if lowered[e] else on_plane[int(owner[e])]).append(sampled[li])
    return on_plane, below, [(int(owner[e]), length) for e, length in unresolved]


def _sample_shares(
    mesh, topo, shares: list[list[int]], chord: float, segment_length: float
) -> tuple[dict[int, Pair], list[tuple[int, float]]]:
    """``_sample_loops`` of each share, one after the other (in a helper)."""
    out: dict[int, Pair] = {}
    unresolved: list[tuple[int, float]] = []
    for ids in shares:
        loops, short = _sample_loops(mesh, topo, ids, chord, segment_length)
        out.update(loops)
        unresolved += short
    return out, unresolved


def _plane_shares(topo, n: int) -> list[list[int]]:
    """The cut's loops in at most ``n`` shares of every ``n``-th plane (neighbouring planes cut much
    the same curves, so the shares take about equal work; by ranges of planes, weighed by their
    topology crossings, the soapbox's upper half took twice its lower half's time); no share empty."""
    by_share: list[list[int]] = [[] for _ in range(n)]
    for li, (j, _) in enumerate(topo.loops):
        by_share[int(j) % n].append(li)
    return [ids for ids in by_share if ids]


def _sample_loops(
    mesh, topo, loop_ids: list[int], chord: float, segment_length: float
) -> tuple[dict[int, Pair], list[tuple[int, float]]]:
    """The (dense loop, corner mask) of each of ``loop_ids``, by a sampler of their own, and the
    segments it could not resolve to the chord (``RingSampler.unresolved``: cut plane, length)."""
    pool = VertexPool()
    # halving: about half the Newton solves of checking every span at the chord (see RingSampler)
    sampler = RingSampler(
        mesh,
        topo,
        pool,
        segment_length=segment_length,
        chord_error=chord,
        keep_crossings=False,
        halving=True,
        gap_ends=False,
        exact_trim=True,
        keep_unresolved=True,
    )
    annulus = topo.comp_is_annulus
    ids = np.asarray(loop_ids, dtype=np.int64)
    free = annulus[topo.loop_below[ids]] & annulus[topo.loop_above[ids]]
    rings = sampler.free_loops(ids[free].tolist())
    for li in ids[~free].tolist():
        rings[li] = sampler.pinned_loop(li)
    xyz = pool.xyz
    return {
        li: (xyz[vids, :2].copy(), np.array([v in sampler.corner_vids for v in vids], dtype=bool))
        for li, vids in rings.items()
    }, sampler.unresolved


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
        pts: list[tuple[float, float]] = []
        exp = TopExp_Explorer(section.Shape(), TopAbs_EDGE)
        while exp.More():
            curve = BRepAdaptor_Curve(TopoDS.Edge(exp.Current()))
            sampler = GCPnts_QuasiUniformDeflection(curve, deflection)
            if sampler.IsDone():
                pts.extend(sampler.Value(i).Coord()[:2] for i in range(1, sampler.NbPoints() + 1))
            exp.Next()
        out.append(np.asarray(pts, dtype=np.float64).reshape(-1, 2))
    return out


def _deflections(used) -> str:
    values = sorted(set(used))
    return " / ".join(f"{d:.3g}" for d in values)


def _reference_topomesh(
    solid, deflection: float, diag: float, parallel: bool = True, repair_precision: float | None = None
):
    """The solid's topology mesh at ``deflection``, or, where BRepMesh's mesh there is not a closed
    manifold (it depends on the deflection: 11752.stp at half the DST build's), at the next of
    ``RETRY_DEFLECTIONS`` times it that is. Returns the mesh, the deflection used, and what was
    repaired (None: the solid as it is).

    Where a face was left unmeshed, the solid is not meshed finer than ``deflection`` before the
    coarser deflections have been tried (up to the build's own, ``repair_precision``) and then,
    if they fail too, the repair the build makes of such a solid (``heal_wires`` to
    ``repair_precision``): if that changes the solid, its repair is meshed instead, from the first
    deflection again. (Where the build meshes the solid as read, at its own deflection or finer
    down to the reference's, one of those deflections meshes it here too.)"""
    order = [deflection * f for f in RETRY_DEFLECTIONS]

    def mesh_of(shape):
        return lambda d: (_topomesh(shape, d, diag, parallel), d)

    unmeshed: UnmeshedFaceError | None = None
    last: TessellationError | None = None
    finer: list[float] = []  # put off until after the coarser ones and the repair
    for d in order:
        if d < deflection and unmeshed is not None and repair_precision is not None:
            finer.append(d)
            continue
        try:
            return (*mesh_of(solid)(d), None)
        except UnmeshedFaceError as exc:  # the last one is named: the build names its own deflection's
            unmeshed = last = exc
        except TessellationError as exc:
            last = exc
    healed = (
        heal_wires(solid, repair_precision) if unmeshed is not None and repair_precision is not None else None
    )
    if healed is None:
        if not finer:
            assert last is not None  # (every deflection was tried: each failed)
            raise last
        return (*_first_that_works(mesh_of(solid), tuple(finer)), None)
    repaired, change = healed
    return (
        *_first_that_works(mesh_of(repaired), tuple(order)),
        f"{unmeshed}; its face boundaries were repaired (gaps closed, edges under {repair_precision:.2g} mm "
        f"dropped; volume changed by {change:.1e} of itself), as the DST build repairs such a solid, and "
        "the exact reference is of the repaired solid",
    )


def _topomesh(solid, deflection: float, diag: float, parallel: bool = True):
    """The topology mesh of ``solid``: BRepMesh's mesh of the solid with its faces that have a pole
    divided (``divide_pole_faces``), as a mesh of the solid's own faces (``_on_solid_faces``), or,
    where BRepMesh's mesh of the divided solid is not a closed manifold (or its parts do not lie on
    their faces' parameters), of the solid as it is."""

    def mesh(shape):
        BRepTools.Clean_s(shape)
        return build_topomesh(
            shape,
            deflection=deflection,
            angular=C.TOPO_ANGULAR_RAD,
            merge_tol=C.MERGE_TOL_REL * diag,
            parallel=parallel,
        )

    divided = divide_pole_faces(solid)
    if divided is not None:
        try:
            return _on_solid_faces(mesh(divided.shape), solid, divided)
        except TessellationError:  # (an unmeshed face too) the solid as it is decides, and names it
            pass
    return mesh(solid)


@dataclass
class DividedSolid:
    """A solid with its faces that have a pole divided (``divide_pole_faces``)."""

    shape: TopoDS_Shape
    face_origin: tuple[int, ...]  # for each face of ``shape``, the solid's face it is part of
    # the edges of ``shape`` the division added (iso curves inside a face, neither an edge of the
    # solid nor a piece of one), numbered from 0 as ``build_topomesh`` numbers its edges
    added_edges: frozenset[int]


def divide_pole_faces(solid: TopoDS_Shape) -> DividedSolid | None:
    """``solid`` with each face that has a pole (a degenerated edge: a sphere's, a revolved profile's
    end on the axis) divided at equal steps of its (u, v) range into POLE_FACE_SPLITS parts, or None
    where it has no such face. The parts keep the face's surface, and the new edges are its iso
    curves, so the solid is the same set of points; only its topology mesh is made faster: BRepMesh's
    Delaunay triangulation of a face in (u, v) is slow where the triangles near a pole are long
    slivers (its circle filter), and takes half the time or less on the face's parts (the B-spline
    hemisphere R = 20 mm at 0.0094 mm: 0.27 s whole, 0.14 s in quarters; the screw of
    boxed_sphere.step at 0.0017 mm: 0.74 s, 0.49 s). Faces without a pole gain nothing on the
    whole (some mesh slower divided), and are left as they are."""
    context = ShapeBuild_ReShape()
    divided = False
    faces = []
    exp = TopExp_Explorer(solid, TopAbs_FACE)
    while exp.More():
        face = exp.Current()
        faces.append(face)
        exp.Next()
        if not _has_pole(face):
            continue
        # divides the face as the context has it (a neighbour's division may have split its edges),
        # recording the parts and its split edges in the shared context
        divide = ShapeUpgrade_ShapeDivideArea(face)
        divide.SetContext(context)
        divide.SetSplittingByNumber(True)
        divide.SetNumbersUVSplits(*POLE_FACE_SPLITS)
        divided |= bool(divide.Perform(False))
    if not divided:
        return None
    result = context.Apply(solid)
    part_of = ShapeIndexedMap()  # the faces each face of ``solid`` became, in its order
    origin = []
    for i, face in enumerate(faces):
        exp = TopExp_Explorer(context.Apply(face), TopAbs_FACE)
        while exp.More():
            part_of.Add(exp.Current())
            origin.append(i)
            exp.Next()
    exp = TopExp_Explorer(result, TopAbs_FACE)
    order = []
    while exp.More():
        k = part_of.FindIndex(exp.Current())
        assert k > 0, "a face of the divided solid that no face of the solid became"
        order.append(origin[k - 1])
        exp.Next()
    edges = ShapeIndexedMap()
    TopExp.MapShapes_s(solid, TopAbs_EDGE, edges)
    solid_edges = ShapeIndexedMap()  # each edge as it is or as the pieces a division split it into
    for i in range(1, edges.Extent() + 1):
        exp = TopExp_Explorer(context.Apply(edges.FindKey(i)), TopAbs_EDGE)
        while exp.More():
            solid_edges.Add(exp.Current())
            exp.Next()
    result_edges = ShapeIndexedMap()
    TopExp.MapShapes_s(result, TopAbs_EDGE, result_edges)
    added = frozenset(
        i - 1
        for i in range(1, result_edges.Extent() + 1)
        if not solid_edges.Contains(result_edges.FindKey(i))
    )
    return DividedSolid(result, tuple(order), added)


def _on_solid_faces(mesh: TopoMesh, solid: TopoDS_Shape, divided: DividedSolid) -> TopoMesh:
    """The topology mesh of ``divided.shape`` as one of ``solid``: each triangle on the face of the
    solid its own face is part of (a part keeps its face's surface and parameters, so its nodes'
    (u, v) are the face's), and the edges a division added (iso curves inside a face) no longer
    B-rep edges. The sections then run across them as across any edge inside a face: no corner, no
    face change and no solve on a B-rep edge there (with them, the B-spline hemisphere's reference
    sampled 1.1% more points, a corner where each loop crossed each such edge), and a message names
    the solid's own faces. Raises TessellationError where a part's surface is not its face's at the
    same (u, v) (a division that reparametrised a surface): the solid is meshed whole."""
    origin = np.asarray(divided.face_origin, dtype=np.int64)
    faces: list[FaceEval] = []
    exp = TopExp_Explorer(solid, TopAbs_FACE)
    while exp.More():
        faces.append(FaceEval(BRepAdaptor_Surface(TopoDS.Face(exp.Current()))))
        exp.Next()
    tri_face = origin[mesh.tri_face]
    # every part's surface and its face's at a few of its corners' (u, v): the same points (the
    # corners themselves can be off both by the file's edge tolerance: a node on an edge is the edge
    # curve's point)
    at_part, at_face = gp_Pnt(), gp_Pnt()
    # each part's triangles in ascending order, grouped by one stable sort (not a scan per part)
    order = np.argsort(mesh.tri_face, kind="stable")
    bounds = np.searchsorted(mesh.tri_face[order], np.arange(len(mesh.faces) + 1))
    for part in range(len(mesh.faces)):
        own = order[bounds[part] : bounds[part + 1]]
        if not len(own):
            continue
        for t in own[np.linspace(0, len(own) - 1, min(8, len(own))).astype(np.int64)].tolist():
            for u, v in mesh.tri_uv[t].tolist():
                mesh.faces[part].ad.D0(u, v, at_part)
                faces[int(origin[part])].ad.D0(u, v, at_face)
                if (gap := at_part.Distance(at_face)) > PART_PARAMETERS_TOL_MM:
                    raise TessellationError(
                        f"face {part + 1} of the divided solid does not keep its face's parameters "
                        f"({gap:.2g} mm apart at the same (u, v))"
                    )
    return replace(
        mesh,
        tri_face=tri_face,
        faces=faces,
        edge_of={key: e for key, e in mesh.edge_of.items() if e not in divided.added_edges},
        filled_faces=tuple((int(origin[f]), area) for f, area in mesh.filled_faces),
        patched_faces=tuple((int(origin[f]), n, d) for f, n, d in mesh.patched_faces),
    )


def _has_pole(face: TopoDS_Shape) -> bool:
    exp = TopExp_Explorer(face, TopAbs_EDGE)
    while exp.More():
        if BRep_Tool.Degenerated_s(TopoDS.Edge(exp.Current())):
            return True
        exp.Next()
    return False


def closed_length(p: np.ndarray) -> float:
    """Length of a closed polyline (k, 2), its last point joined to its first."""
    return float(np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1).sum())
