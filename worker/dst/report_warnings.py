"""The warnings of a deviation report that need more than a glance at its numbers: a DST ring vertex
on the B-rep but off the exact reference (a gap of the reference, or a file exact only to its
tolerances), or both off the B-rep across a gap of its faces; a DST contour crossing itself (or
across a neck of the section); a reference out of order where the meshes deviate most; a needle of
the exact section or a loose edge where DST is over its budget; a mesh not watertight or off in
volume; a measured mesh not in the part's coordinates.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from OCP.Bnd import Bnd_Box
from OCP.BRep import BRep_Tool
from OCP.BRepAdaptor import BRepAdaptor_Surface
from OCP.BRepBndLib import BRepBndLib
from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeVertex
from OCP.BRepExtrema import BRepExtrema_DistShapeShape
from OCP.collections import IndexedMap_TopoDS_Shape_TopTools_ShapeMapHasher as ShapeIndexedMap
from OCP.gp import gp_Pnt
from OCP.ShapeAnalysis import ShapeAnalysis_Surface
from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE
from OCP.TopExp import TopExp, TopExp_Explorer
from OCP.TopoDS import TopoDS, TopoDS_Edge, TopoDS_Face

from worker.dst.chords import chord_position
from worker.dst.cuts import cut_mesh, loop_needles, loop_self_crossings
from worker.dst.deviation import SegmentSet
from worker.dst.exact import FaceEval
from worker.dst.report_schema import MeshReport
from worker.dst.sampler_records import unresolved_summary
from worker.dst.step_io import LoadedPart
from worker.dst.topomesh import max_tolerance

if TYPE_CHECKING:
    from worker.dst.measure import MeshInput, Placed


VOLUME_WARN_REL = 0.01  # a mesh enclosing 1% more or less than the solid is worth a warning
# A DST ring vertex this far from the exact reference (mm) is checked against the B-rep: lying on it,
# it shows a part of the section the reference missed (its own topology mesh passed between the plane
# and a nearby crest), not a deviation of the mesh. At most this many planes are checked.
REFERENCE_GAP_MM = 2e-3
REFERENCE_GAP_PLANES = 20
# Each mesh's planes of largest chord_dev (and of perimeter_err) whose reference is checked for
# crossing itself (``reference_fault_warning``)
REFERENCE_CHECK_PLANES = 5
# ... crossing only where each segment's ends lie farther than this (mm) on either side of the other's
# line: where two faces of the part touch along a line, the section runs along it twice, its passes
# as far apart as rounding puts them (trj7_b1-ec-214 at z = 56.9: up to 1e-9 mm, read as crossings
# round a 94 mm^2 "pocket", a whole lobe). A crossing of two of the thinned loop's segments (a tenth
# of the budget long or more) is left out only where it passes within a nanometre of a segment's end
# or the two run within a nanometre of each other
REFERENCE_TOUCH_MM = 1e-6
# ... among each piece's this many nearest pieces (bug27453_165-174 at z = 37.1: 3500 points of the
# reference within 0.24 mm, 12 million pairs, 20 s for all of them)
REFERENCE_PAIR_NEIGHBOURS = 16


def reference_gap_warnings(
    part: LoadedPart,
    dst: Placed,
    result: MeshReport,
    ref_set: SegmentSet,
    heights: np.ndarray,
    zmin: float,
    flat_planes: list[int],
) -> list[str]:
    """Warnings for the planes where DST's ring vertices (``dst``: its mesh as placed) lie more than ``REFERENCE_GAP_MM`` from the
    exact reference although the farthest of them lies on the B-rep (a ring vertex is an exact B-rep
    point on its plane, stored as float32): where it is farther from the reference than its face's
    edge tolerances, the reference misses part of the section; where it is within them, the file's
    faces and edges disagree by that much there, and the section is only defined to that tolerance.
    A vertex on no face is the mesh's own deviation, unless the reference's point nearest it lies on
    no face either: then the B-rep itself has a gap there (its faces' section curves stop short of
    each other), which the reference bridges straight and the ring on a face's surface past its trim
    (trj7_b1-ec-214 turned (-99.8, 126.0, -162.8): 0.3-1.6 mm gaps at six planes, the ring up to
    0.196 mm from the reference's bridge, each 0.1-0.35 mm off every face)."""
    flat = set(flat_planes)
    suspect = [
        layer.index
        for layer in sorted(result.layers, key=lambda layer: -(layer.vertex_dev or 0.0))
        if (layer.vertex_dev or 0.0) > REFERENCE_GAP_MM and layer.index not in flat
    ][:REFERENCE_GAP_PLANES]
    if not suspect:
        return []
    js = np.array(sorted(suspect))
    cut = cut_mesh(dst.vertices, dst.triangles, heights[js])
    plane = js[cut.vertex_plane]
    d, span = ref_set.nearest(cut.vertices, plane)
    faces = _faces_with_boxes(part)
    gaps: list[tuple[int, float]] = []  # (plane, distance)
    loose: list[tuple[int, float, float]] = []  # (plane, distance, the face's edge tolerance)
    bridged = []  # (plane, distance, the reference's and the vertex's distance to the faces, span length)
    for k, j in enumerate(js.tolist()):
        mine = np.flatnonzero(cut.vertex_plane == k)
        if not len(mine):
            continue
        far = mine[np.argmax(d[mine])]
        x, y = cut.vertices[far]
        p = (float(x), float(y), float(zmin + heights[j]))
        # the vertex as its STL holds it: float32, a few ulps of its largest coordinate off the B-rep
        tol = 4.0 * float(np.spacing(np.float32(max(abs(c) for c in p)))) + 1e-7
        face_tol = _on_a_face(faces, p, tol)
        if face_tol is None:
            a, b = ref_set.seg[span[far]]
            q = a + np.clip(chord_position(cut.vertices[far][None], a[None], b[None])[0], 0.0, 1.0) * (b - a)
            off_ref = _distance_to_faces(faces, (float(q[0]), float(q[1]), p[2]))
            if off_ref > REFERENCE_GAP_MM:
                off_dst = _distance_to_faces(faces, p)
                bridged.append((j, float(d[far]), off_ref, off_dst, float(np.linalg.norm(b - a))))
            continue
        # farther from the reference than the face's own edges are from it (the file's tolerance):
        # in a file whose faces and edges disagree, both may be on "the B-rep" and still differ
        if d[far] > face_tol:
            gaps.append((j, float(d[far])))
        else:
            loose.append((j, float(d[far]), face_tol))
    out = []
    if gaps:
        worst = max(gaps, key=lambda g: g[1])
        planes = ", ".join(str(j) for j, _ in gaps)
        out.append(
            f"the exact reference misses part of the section at {len(gaps)} plane(s) ({planes}; the largest "
            f"at plane {worst[0]}, z = {result.layers[worst[0]].z:.4f} mm): a DST ring vertex there lies on "
            f"a face of the B-rep yet {worst[1]:.3g} mm from the reference, more than that face's edge "
            "tolerances (the reference's own topology mesh passed between the plane and a crest close to "
            "it). At those planes the DST mesh's vertex_dev and chord_dev measure the reference's gap, not "
            "the mesh, and every mesh's numbers are uncertain by as much"
        )
    if bridged:
        j, dist, off_ref, off_dst, length = max(bridged, key=lambda g: g[1])
        planes = ", ".join(str(g[0]) for g in bridged)
        out.append(
            f"the B-rep leaves a gap in the section at {len(bridged)} plane(s) ({planes}; the largest at "
            f"plane {j}, z = {result.layers[j].z:.4f} mm): no face holds the section there (the file's "
            "faces stop short of each other), so there is no exact contour to measure against. The exact "
            f"reference bridges the gap straight ({length:.3g} mm, its point nearest the DST ring "
            f"{off_ref:.3g} mm off every face) and the DST ring follows a face's surface past its trim "
            f"({off_dst:.3g} mm off every face), {dist:.3g} mm apart. At those planes every mesh's vertex_dev "
            "and chord_dev measure its way across the gap against the reference's, not its deviation "
            "from the part"
        )
    if loose:
        loosest = max(loose, key=lambda g: g[1])
        planes = ", ".join(str(j) for j, _, _ in loose)
        out.append(
            f"the file is exact only to its tolerances at {len(loose)} plane(s) ({planes}; the largest at "
            f"plane {loosest[0]}, z = {result.layers[loosest[0]].z:.4f} mm): a DST ring vertex there lies on a "
            f"face of the B-rep yet {loosest[1]:.3g} mm from the exact reference, within the "
            f"{loosest[2]:.3g} mm tolerance of that face's edges (its boundary and its neighbours' disagree "
            "by up to that much, so both sections lie on the B-rep). There the DST mesh's vertex_dev and "
            "chord_dev measure the file's tolerance, not the mesh"
        )
    return out


@dataclass
class _FaceProbe:
    """A face, its box grown by 0.001 mm (more than any point's float32 rounding ``_on_a_face``
    allows: a filter, the projection decides), and its projector and trim test, made when first
    needed and then kept (a projector builds a grid over its surface on first use)."""

    face: TopoDS_Face
    box: Bnd_Box
    _surface: ShapeAnalysis_Surface | None = None
    _eval: FaceEval | None = None

    def on_face(self, q: gp_Pnt, tol: float) -> bool:
        """Does ``q`` lie within ``tol`` of the surface, inside the face's trim?"""
        if self.box.IsOut(q):
            return False
        if self._surface is None or self._eval is None:
            self._surface = ShapeAnalysis_Surface(BRep_Tool.Surface_s(self.face))
            self._eval = FaceEval(BRepAdaptor_Surface(self.face))
        u, v = self._surface.ValueOfUV(q, tol).Coord()
        return self._surface.Gap() <= tol and self._eval.contains(u, v, tol=1e-6)


def _faces_with_boxes(part: LoadedPart) -> list[_FaceProbe]:
    out = []
    exp = TopExp_Explorer(part.compound, TopAbs_FACE)
    while exp.More():
        face = TopoDS.Face(exp.Current())
        exp.Next()
        box = Bnd_Box()
        BRepBndLib.Add_s(face, box, False)
        box.Enlarge(1e-3)
        out.append(_FaceProbe(face, box))
    return out


def _distance_to_faces(faces: list[_FaceProbe], p: tuple[float, float, float]) -> float:
    """Distance (mm) from ``p`` to the nearest of the faces, each within its trim (inside a solid
    or not: faces, not volumes)."""
    lo = np.array([f.box.CornerMin().Coord() for f in faces])
    hi = np.array([f.box.CornerMax().Coord() for f in faces])
    x = np.asarray(p)
    to_box = np.linalg.norm(np.maximum(np.maximum(lo - x, x - hi), 0.0), axis=1)
    vertex = BRepBuilderAPI_MakeVertex(gp_Pnt(*p)).Vertex()
    best = np.inf
    for k in np.argsort(to_box).tolist():  # nearest boxes first, until a box lies beyond the best
        if to_box[k] > best:
            break
        dist = BRepExtrema_DistShapeShape(vertex, faces[k].face)
        if dist.IsDone():
            best = min(best, dist.Value())
    return float(best)


def _on_a_face(faces: list[_FaceProbe], p: tuple[float, float, float], tol: float) -> float | None:
    """If ``p`` lies within ``tol`` of a face's surface, inside that face's trim: the largest
    tolerance of that face's edges (how far its boundary may be from its neighbours'); else None. (A
    point on an edge its faces do not meet, in a file with large edge tolerances, is not on a face.)"""
    q = gp_Pnt(*p)
    for probe in faces:
        if probe.on_face(q, tol):
            return max_tolerance(probe.face, TopAbs_EDGE)
    return None


def self_crossing_warnings(
    pockets: list[tuple[int, float, float, float, float]],
    planes_z: np.ndarray,
    chord: float,
    ref_loops: list[list[np.ndarray]],
) -> list[str]:
    """The warnings for a DST mesh whose contour crosses itself round more than a chord-budget
    square at some plane (``cuts.self_crossings``: plane, area, length, x, y; bow ties of points out
    of order by micrometres, with no such pocket, are left out). A crossing where the exact section
    (``ref_loops``) itself pinches to a neck narrower than the budget is told apart: there the
    section's two sides run within the budget of each other (two faces touching, or a zero-width
    strip between two lobes: trj7_b1-ec-214 turned (-99.8, 126.0, -162.8) at z = 101.7, a doubled
    0.37 mm stretch), the ring's two passes along it cross by micrometres, and the pocket the shorter
    way round is a whole lobe (1168 mm^2 there), not a fault of the build's."""
    big = [p for p in pockets if p[1] > chord * chord]
    faults: list[tuple[int, float, float, float, float]] = []
    necks: list[tuple[int, float, float, float, float]] = []
    for p in big:
        at_neck = np.isfinite(p[1]) and _at_a_neck(ref_loops[p[0]], np.array(p[3:5]), chord)
        (necks if at_neck else faults).append(p)
    out = []
    if faults:
        j, area = max(faults, key=lambda p: p[1])[:2]
        planes = sorted({p[0] for p in faults})
        size = "a strip where the contour turns over" if not np.isfinite(area) else f"{area:.3g} mm^2"
        out.append(
            f"the DST mesh's contour crosses itself at {len(planes)} plane(s) (the largest pocket: {size}, "
            f"at z = {planes_z[j]:.4f} mm): a fault of this build (its ring out of order there, or a strip "
            "of its triangles folded over) that slicers see as a self-intersecting outline, and that the "
            "per-layer deviations need not show"
        )
    if necks:
        planes = sorted({p[0] for p in necks})
        out.append(
            f"the DST mesh's contour runs along itself across a neck of the exact section at {len(planes)} "
            f"plane(s) ({', '.join(f'z = {planes_z[j]:.4f} mm' for j in planes[:5])}"
            f"{', ...' if len(planes) > 5 else ''}): the section pinches there to less than the "
            f"{chord:g} mm chord budget (two faces touching, or passing within the file's tolerance), and "
            "the ring's two passes along it cross each other. Slicers that take the outline as drawn see "
            "it cross itself there; those that unite its polygons (PrusaSlicer, Cura) close it. The "
            "per-layer deviations are not affected"
        )
    return out


def _at_a_neck(loops: list[np.ndarray], c: np.ndarray, r: float) -> bool:
    """Whether the closed loops pass within ``r`` of point ``c`` twice: two loops, or two stretches
    of one loop more than 2 ``r`` apart along it both ways round."""
    passes = 0
    for p in loops:
        q = np.roll(p, -1, axis=0)
        ab = q - p
        t = np.clip(
            np.einsum("ij,ij->i", c - p, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300), 0, 1
        )
        near = np.linalg.norm(p + t[:, None] * ab - c, axis=1) <= r
        if not near.any():
            continue
        if near.all():
            passes += 1
            continue
        # stretches of consecutive near spans (the first joined to the last round the loop's start),
        # each at its arc length along the loop; two closer than 2 r along it are one pass
        length = np.linalg.norm(ab, axis=1)
        s = np.concatenate([[0.0], np.cumsum(length)])
        total = s[-1]
        first = np.flatnonzero(near & ~np.roll(near, 1))
        last = np.flatnonzero(near & ~np.roll(near, -1))
        starts, ends = s[first], s[last + 1]
        ends = np.where(ends < starts, ends + total, ends)  # (a stretch over the loop's start)
        order = np.argsort(starts)
        starts, ends = starts[order], ends[order]
        gaps = np.append(starts[1:] - ends[:-1], starts[0] + total - ends[-1])
        passes += max(1, int((gaps > 2.0 * r).sum()))
    return passes >= 2


def reference_fault_warning(
    loops: list[list[np.ndarray]],
    results: list[MeshReport],
    planes_z: np.ndarray,
    chord_error: float,
    resolution: float,
) -> str | None:
    """The warning for an exact reference that crosses itself round more than a chord-budget square
    (``cuts.loop_self_crossings``: the pockets ``self_crossings`` finds) at a plane that holds a
    mesh's largest deviations: its points are exact, but out of order there (a plane grazing a crest,
    or passing a saddle, where the sampler's traces fail), and the meshes' chord_dev and perimeter_err
    at that plane may measure the reference. Looked for where it matters and is cheap: each mesh's
    ``REFERENCE_CHECK_PLANES`` planes of largest chord_dev and of largest perimeter_err, and every
    plane where DST is over its budget (a search of every plane costs 0.2 s on ec_soapbox-A)."""
    check: set[int] = set()
    for r in results:
        chord_dev = np.array([np.nan if x.chord_dev is None else x.chord_dev for x in r.layers])
        perimeter = np.array([np.nan if x.perimeter_err is None else x.perimeter_err for x in r.layers])
        for values in (chord_dev, perimeter):
            ok = np.flatnonzero(np.isfinite(values))
            check.update(ok[np.argsort(-values[ok], kind="stable")[:REFERENCE_CHECK_PLANES]].tolist())
    check.update(_dst_over_budget(results, chord_error, resolution))
    # thinned to a point per tenth of the budget along each loop: a reference tangled into
    # thousands of points micrometres apart (trj7 at z = 56.9: 7000 at one plane) otherwise takes
    # seconds in the pair search, for pockets within that tenth of their own size
    step = 0.1 * chord_error
    pockets = loop_self_crossings(
        [[_thinned(p, step) for p in ls] if j in check else [] for j, ls in enumerate(loops)],
        nearest=REFERENCE_PAIR_NEIGHBOURS,
        tol=REFERENCE_TOUCH_MM,
    )
    big = [(j, area) for j, area, _ in pockets if area > chord_error * chord_error]
    if not big:
        return None
    j, area = max(big, key=lambda p: p[1])
    planes = sorted({p[0] for p in big})
    return (  # (closed loops in order: every pocket is finite)
        f"the report's exact reference is out of order at {len(planes)} plane(s) that hold the meshes' "
        f"largest deviations (the largest pocket between its crossing segments: {area:.3g} mm^2, at z = "
        f"{planes_z[j]:.4f} mm; plane(s) {', '.join(map(str, planes[:10]))}): its points lie on the "
        "section but are joined in the wrong order there (a plane grazing a crest or passing near a "
        "saddle, or faces and edges that disagree), so the meshes' chord_dev and perimeter_err at those "
        "planes, and the summaries they set, may measure the reference's fault rather than the meshes'"
    )


def reference_needle_warning(
    loops: list[list[np.ndarray]],
    results: list[MeshReport],
    planes_z: np.ndarray,
    chord_error: float,
    resolution: float,
) -> str | None:
    """The warning for planes where the DST mesh is over its chord budget and the exact section has
    a needle longer than that budget (``cuts.loop_needles``, its legs within the reference's
    ``resolution`` of each other): a spike out and back along itself, or the thin end of a cusp,
    which encloses no material. The ring need not follow it (bug27453_165-174_piattello turned
    (129.5, 111.3, 134.0) at z = 38.1: a spike 0.034 mm long on the B-rep, its legs 17 nm apart, and
    DST's chord_dev there 0.034 mm; trj7_b1-ec-214 turned (-77.1, -176.1, -133.9) at z = 67.1: a face
    doubling its neighbour within 5 um, and a spike 0.14 mm out and back on it), so DST's chord_dev
    at such a plane may be the needle's length rather than an error of any printed contour."""
    over = _dst_over_budget(results, chord_error, resolution)
    found = [
        (j, length) for j in over for p in loops[j] for length, _ in loop_needles(p, resolution, chord_error)
    ]
    if not found:
        return None
    j, length = max(found, key=lambda f: f[1])
    planes = sorted({f[0] for f in found})
    return (
        f"the DST mesh is over its {chord_error:g} mm chord budget at {len(planes)} plane(s) where the exact "
        f"section has a needle longer than that and narrower than {resolution * 1000:g} um (the longest "
        f"{length:.3g} mm, at z = {planes_z[j]:.4f} mm; plane(s) {', '.join(map(str, planes[:10]))}"
        f"{', ...' if len(planes) > 10 else ''}): a spike out and back along itself or the thin end of a "
        "cusp (faces meeting at a tangent, or one doubling another within the file's tolerance), which "
        "encloses no material and which no slicer prints. A mesh that does not follow it to its tip reads "
        "up to its length in chord_dev there"
    )


# At most this many exact points over DST's budget are checked against the B-rep's edges
# (``edge_tolerance_warning``); with more, no plane is named
EDGE_CHECK_POINTS = 2000


def edge_tolerance_warning(
    part: LoadedPart,
    dst: Placed,
    results: list[MeshReport],
    loops: list[list[np.ndarray]],
    heights: np.ndarray,
    zmin: float,
    planes_z: np.ndarray,
    chord_error: float,
    resolution: float,
) -> str | None:
    """The warning for planes where the DST mesh is over its chord budget only at exact points that
    lie within the tolerance of a B-rep edge, each no farther from the DST ring than the budget and
    that edge's tolerance together: there the faces on either side of the edge, and the edge itself,
    disagree by up to that tolerance (each face's section ends at its own boundary, and the file
    joins them only within the tolerance), so the exact section is defined only to it. A chord budget below a
    file's edge tolerances meets this at its loose edges: ``boxed_sphere`` turned (22.6, 70.6,
    -54.5) at chord_error 0.005 mm, z = 9.1, where face 127's section ends 18 um from edge 561
    (tolerance 0.055 mm) and the ring, joining the edge's own crossing, passes 0.0156 mm from that
    end. A plane with a point over budget that is not so explained is not named (nor is any, past
    ``EDGE_CHECK_POINTS`` points)."""
    over = _dst_over_budget(results, chord_error, resolution)
    if not over:
        return None
    js = np.array(sorted(set(over)))
    cut = cut_mesh(dst.vertices, dst.triangles, heights[js])
    ring = SegmentSet(cut.seg, cut.seg_plane)
    pts, plane = [], []
    for k, j in enumerate(js.tolist()):
        for p in loops[j]:
            pts.append(p[:, :2])
            plane.append(np.full(len(p), k))
    if not pts:
        return None
    xy, plane_k = np.concatenate(pts), np.concatenate(plane)
    d = ring.distance(xy, plane_k)
    far = np.flatnonzero(d > chord_error + resolution + 1e-6)
    if not len(far) or len(far) > EDGE_CHECK_POINTS:
        return None
    # the farthest first: a plane's first point not so explained leaves it unnamed
    order = far[np.argsort(-d[far])]
    xyz = np.column_stack([xy[order], zmin + heights[js[plane_k[order]]]])
    tols = edge_tolerances(part, xyz, d[order] - chord_error)
    named: dict[int, tuple[float, float]] = {}  # plane -> (largest distance, its edge's tolerance)
    unexplained: set[int] = set()
    for i, tol in zip(order.tolist(), tols.tolist(), strict=True):
        k = int(plane_k[i])
        if not np.isfinite(tol):
            unexplained.add(k)
            named.pop(k, None)
        elif k not in unexplained and k not in named:
            named[k] = (float(d[i]), tol)
    if not named:
        return None
    planes = sorted(int(js[k]) for k in named)
    k, (dist, tol) = max(named.items(), key=lambda item: item[1][0])
    return (
        f"the DST mesh is over its {chord_error:g} mm chord budget at {len(planes)} plane(s) only where the "
        f"exact section runs within the tolerance of a B-rep edge (plane(s) {', '.join(map(str, planes[:10]))}"
        f"{', ...' if len(planes) > 10 else ''}; the largest, {dist:.3g} mm, at z = "
        f"{planes_z[int(js[k])]:.4f} mm, by an edge of tolerance {tol:.3g} mm): there the "
        "faces on either side of the edge and the edge itself disagree by up to that tolerance, so the "
        "section is defined only to it, and the DST ring is within its budget of the section so "
        "defined: the file itself is no more exact there than its edge tolerances, which are coarser "
        "than the chord_error asked for"
    )


@dataclass
class _EdgeProbe:
    """An edge, its tolerance and its box grown by that tolerance (a filter: the distance decides)."""

    edge: TopoDS_Edge
    tol: float
    box: Bnd_Box


def _edges_with_boxes(part: LoadedPart, min_tol: float) -> list[_EdgeProbe]:
    """The part's edges (each once, degenerate ones left out) whose tolerance is at least ``min_tol``."""
    edges = ShapeIndexedMap()
    TopExp.MapShapes_s(part.compound, TopAbs_EDGE, edges)
    out = []
    for i in range(1, edges.Extent() + 1):
        edge = TopoDS.Edge(edges.FindKey(i))
        tol = BRep_Tool.Tolerance_s(edge)
        if tol < min_tol or BRep_Tool.Degenerated_s(edge):
            continue
        box = Bnd_Box()
        BRepBndLib.Add_s(edge, box, False)
        box.Enlarge(tol)
        out.append(_EdgeProbe(edge, tol, box))
    return out


def edge_tolerances(part: LoadedPart, points: np.ndarray, dists: np.ndarray) -> np.ndarray:
    """For each point (n, 3; the part's coordinates), the largest tolerance among the B-rep edges
    within whose tolerance it lies (its distance to the edge's curve) and whose tolerance is at least
    its ``dists`` entry (the part of a deviation the tolerance must explain); NaN where there is
    none."""
    out = np.full(len(points), np.nan)
    if not len(points):
        return out
    edges = _edges_with_boxes(part, float(np.min(dists)))  # (in a tight file: none)
    for i, (p, dist) in enumerate(zip(points.tolist(), np.asarray(dists).tolist(), strict=True)):
        q = gp_Pnt(*p)
        vertex = BRepBuilderAPI_MakeVertex(q).Vertex()
        for probe in edges:
            if probe.tol < dist or probe.tol <= out[i] or probe.box.IsOut(q):  # (NaN compares False)
                continue
            ext = BRepExtrema_DistShapeShape(vertex, probe.edge)
            if ext.IsDone() and ext.Value() <= probe.tol:
                out[i] = probe.tol
    return out


def _dst_over_budget(results: list[MeshReport], chord_error: float, resolution: float) -> list[int]:
    """The planes where the DST mesh's chord_dev is over its budget by more than the reference's
    resolution (none without a DST mesh)."""
    out: list[int] = []
    for r in results:
        if r.kind == "dst":
            chord_dev = np.array([np.nan if x.chord_dev is None else x.chord_dev for x in r.layers])
            out += np.flatnonzero(chord_dev > chord_error + resolution + 1e-6).tolist()
    return out


def unresolved_reference_warning(
    unresolved: list[tuple[int, float]], planes_z: np.ndarray, resolution: float
) -> str | None:
    """The warning for an exact reference whose sampling left segments over its resolution after
    its last round (``ExactSections.unresolved``: (plane, length) each), rather than failing the
    report: trj7_b1-ec-214 turned (-33.7, -98.1, 159.6), a corner 2.6 um off its face's curve
    (edge tolerances up to 0.3 mm), where every point solved between them landed at the curve."""
    if not unresolved:
        return None
    planes, j, longest = unresolved_summary(unresolved)
    return (
        f"the exact reference could not be refined to its {resolution:g} mm resolution everywhere: "
        f"{len(unresolved)} segment(s) at {len(planes)} plane(s) ({', '.join(map(str, planes[:10]))}"
        f"{', ...' if len(planes) > 10 else ''}; the longest, {longest:.3g} mm, at z = "
        f"{planes_z[j]:.4f} mm) still failed its check after the last round (where faces and edges "
        "disagree, a corner off its face's curve by the file's tolerance). There the reference joins "
        "two exact points by a straight segment without following the curve between them, and each "
        "mesh's chord_dev and perimeter_err at those planes may be off by as much as that segment is "
        "long"
    )


def _thinned(loop: np.ndarray, step: float) -> np.ndarray:
    """The closed polyline ``loop`` with only the first of its points in each ``step`` of arc length."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(loop, axis=0), axis=1))])
    return loop[np.concatenate([[True], np.diff(np.floor(s / step)) > 0])]


def mesh_warnings(r: MeshReport) -> list[str]:
    out = []
    s = r.summary
    if s.layers_missing:
        out.append(
            f"{r.name}: {s.layers_missing} layer(s) where the part has a section but the mesh has none"
        )
    if s.layers_extra:
        out.append(f"{r.name}: {s.layers_extra} layer(s) where the mesh has a section but the part has none")
    if not r.watertight:
        out.append(
            f"{r.name}: the mesh is not watertight ({r.open_edges} open and {r.nonmanifold_edges} non-manifold "
            "edges); slicers must guess its contours"
        )
    if r.volume_rel_err is not None and abs(r.volume_rel_err) > VOLUME_WARN_REL:
        out.append(f"{r.name}: encloses {100 * r.volume_rel_err:+.1f}% of the exact volume")
    return out


def placement_warnings(todo: Sequence[MeshInput], lo: tuple, hi: tuple) -> list[str]:
    out = []
    size = max(hi[0] - lo[0], hi[1] - lo[1])
    for m in todo:
        if m.kind != "input" or not len(m.vertices):
            continue
        mlo, mhi = m.vertices[:, :2].min(axis=0), m.vertices[:, :2].max(axis=0)
        off = float(np.max(np.abs(np.concatenate([mlo - lo, mhi - hi]))))
        if off > max(1.0, 0.05 * size):
            out.append(
                f"{m.name}: its x/y extent differs from the part's by up to {off:.3g} mm: is it placed in the "
                "STEP file's coordinates (not centred or moved by a slicer)? Distances assume it is"
            )
    return out
