"""STEP in, DST mesh out: the whole core for one part, with its statistics and warnings."""

from __future__ import annotations

import functools
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np
from OCP.Bnd import Bnd_Box
from OCP.BRepBndLib import BRepBndLib
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from worker.dst import constants as C
from worker.dst.errors import ResourceLimitExceeded, TessellationError, UnmeshedFaceError
from worker.dst.lowest import snap_extremes
from worker.dst.meshops import (
    crowded_edges,
    drop_unreferenced,
    edge_defects,
    repeated_corner,
    signed_volume,
    split_t_junctions,
    unique_ints,
)
from worker.dst.params import SliceParams
from worker.dst.planes import PlanePlan, plan_planes
from worker.dst.ridges import prepare_extremes
from worker.dst.sampler_records import SamplingStats, VertexPool, unresolved_summary
from worker.dst.sampling import RingSampler
from worker.dst.sections import cut_topology
from worker.dst.step_io import LoadedPart, heal_wires, orient, read_step
from worker.dst.stl_io import merge_equal_vertices, write_3mf, write_stl
from worker.dst.tessellate import tessellate_solid
from worker.dst.topomesh import TopoMesh, build_topomesh

Progress = Callable[[str, float], None]

# ``unfold_float32``: a fold of a ring merged only within this many float32 steps of its
# coordinates (bug27693_cornetta's: ~3), in at most this many rounds of merges
FOLD_ULPS = 8
FOLD_ROUNDS = 8


@dataclass
class DstMesh:
    """A finished DST mesh.

    vertices : (V, 3) float64, mm; part placed with its exact lowest point at z = 0, x and y unchanged
    triangles : (F, 3) int64, counter-clockwise seen from outside
    vertex_plane : (V,) int64, index of the plane a ring vertex lies on, else -1
    planes : the slicing planes (heights above the part's lowest point)
    """

    vertices: np.ndarray
    triangles: np.ndarray
    vertex_plane: np.ndarray
    planes: PlanePlan
    z_offset: float
    part: LoadedPart
    params: SliceParams
    warnings: list[str] = field(default_factory=list)
    stats: dict = field(default_factory=dict)

    @property
    def vertices32(self) -> np.ndarray:
        """(V, 3) float32 as written to STL; ring vertices' z is exactly ``float32(plane)``."""
        return float32_vertices(self.vertices, self.vertex_plane, self.planes.z32)

    def write_stl(self, path: str | os.PathLike[str], *, ascii: bool = False) -> int:
        return write_stl(path, self.vertices32, self.triangles, ascii=ascii)

    def write_3mf(self, path: str | os.PathLike[str]) -> int:
        return write_3mf(path, self.vertices32, self.triangles)


def slice_step(
    path: str | os.PathLike[str], params: SliceParams, *, progress: Progress | None = None
) -> DstMesh:
    """Read ``path`` and build its DST mesh for ``params``."""
    report = progress or (lambda stage, frac: None)
    t0 = time.perf_counter()
    report("reading STEP", 0.0)
    part = read_step(path)
    return slice_part(part, params, progress=report, t0=t0)


def slice_part(
    part: LoadedPart,
    params: SliceParams,
    *,
    progress: Progress | None = None,
    t0: float | None = None,
    helper: bool = True,
) -> DstMesh:
    """The DST mesh of ``part`` for ``params``, the part first turned by ``params.rotation`` (the
    mesh's ``part`` is the turned one: what its report must measure against). ``helper``: half the
    free loops may be sampled in a forked helper on an idle core (``tessellate.free_rings``); the
    mesh is the same either way."""
    report = progress or (lambda stage, frac: None)
    t0 = time.perf_counter() if t0 is None else t0
    part = orient(part, params.rotation)  # the part itself if it is turned already (or not to be)
    timings: dict[str, float] = {"read": time.perf_counter() - t0}
    warnings = list(part.warnings)

    diag, loose_height = bbox_diagonal(part)
    plan_planes(height=loose_height, params=params)  # refuse absurd plane counts before any meshing
    deflection = build_deflection(diag, params)
    t = time.perf_counter()
    meshes = []
    topomesh = functools.partial(
        build_topomesh, deflection=deflection, angular=C.TOPO_ANGULAR_RAD, merge_tol=C.MERGE_TOL_REL * diag
    )
    for si, solid in enumerate(part.solids):
        report(f"meshing solid {si + 1}/{len(part.solids)}", 0.1 * si / len(part.solids))
        try:
            mesh = _topomesh_or_finer(topomesh, solid, deflection)
        except UnmeshedFaceError as exc:
            # A face OCCT cannot mesh often has gaps or zero-length edges in its boundary: repaired
            # within the mesh's own deflection, the same solid is meshed again (and is the one the
            # sections and the report use). Without a repair, or if it does not help, the first error.
            healed = heal_wires(solid, deflection)
            if healed is None:
                raise
            solid, change = healed
            try:
                mesh = _topomesh_or_finer(topomesh, solid, deflection)
            except TessellationError:
                raise exc from None
            part.solids[si] = solid
            warnings.append(
                f"solid {si + 1}: {exc}; its face boundaries were repaired (gaps closed, edges under "
                f"{deflection:.2g} mm dropped; volume changed by {change:.1e} of itself) and it was meshed"
            )
        meshes.append(mesh)
    timings["topomesh"] = time.perf_counter() - t
    for si, mesh in enumerate(meshes):
        for face, area in mesh.filled_faces:
            warnings.append(
                f"solid {si + 1}: OCCT could not mesh face {face + 1} (a sliver of {area:.2g} mm^2, "
                "smaller than the mesh tolerance); its hole was closed from the neighbouring faces"
            )
        if mesh.dropped_triangles:
            warnings.append(
                f"solid {si + 1}: {mesh.dropped_triangles} triangle(s) of OCCT's mesh folded a face over "
                "or lay on a neighbouring face and were dropped"
            )
        for face, n_tris, dist in mesh.patched_faces:
            warnings.append(
                f"solid {si + 1}: a hole OCCT's mesh left in face {face + 1} (a sliver between nearly "
                f"coincident edges) was closed with {n_tris} triangle(s) within {dist:.2g} mm of the face"
            )
        if mesh.merged_open_nodes:
            warnings.append(
                f"solid {si + 1}: {mesh.merged_open_nodes} mesh node(s) on cracks were merged within "
                "the file's own vertex tolerance to close the surface"
            )

    t = time.perf_counter()
    zmin, zmax = snap_extremes(meshes)
    height = zmax - zmin
    planes = plan_planes(height=height, params=params)
    world = zmin + planes.section_z
    # half the float32 spacing at each plane: a node closer than that is written onto the plane
    float32_resolution = 0.5 * np.spacing(np.abs(planes.z32)).astype(np.float64)
    prepared = [prepare_extremes(mesh, world, float32_resolution) for mesh in meshes]
    local_extremes = sum(snapped for snapped, _, _ in prepared)
    ridge_nodes = sum(added for _, added, _ in prepared)
    grazed_nodes = sum(added for _, _, added in prepared)
    timings["extremes"] = time.perf_counter() - t

    topos = []
    estimate = 0.0
    for mesh in meshes:
        t = time.perf_counter()
        topo = cut_topology(mesh, world, on_plane_tol=C.ON_PLANE_TOL_MM, noise_tol=float32_resolution)
        timings["sections"] = timings.get("sections", 0.0) + time.perf_counter() - t
        topos.append(topo)
        estimate += estimated_triangles(topo, params)
    if estimate > C.MAX_TRIANGLES:
        raise ResourceLimitExceeded(
            f"this part would need about {estimate / 1e6:.0f} million triangles at {params.layer_height} mm layers "
            f"and {params.segment_length} mm segments (limit {C.MAX_TRIANGLES / 1e6:.0f} million): "
            "check the file's units, or use thicker layers or longer segments"
        )

    pool = VertexPool()
    flat_planes: set[int] = set()
    all_tris: list[np.ndarray] = []
    stats: dict = {
        "solids": len(part.solids),
        "planes": len(planes),
        "height_mm": height,
        "local_extremes_snapped": local_extremes,
        "ridge_nodes": ridge_nodes,
        "grazed_nodes": grazed_nodes,
        "t_junctions": 0,  # triangles split where a collapsed piece left one (see split_t_junctions)
    }
    sampling_totals = SamplingStats()
    unresolved: list[tuple[int, float]] = []  # (plane, length) of segments kept over budget
    for si, (mesh, topo) in enumerate(zip(meshes, topos, strict=True)):
        frac = 0.1 + 0.85 * si / len(meshes)
        flat_planes.update(topo.flat_planes)
        report(f"sampling solid {si + 1}/{len(part.solids)}", frac)
        t = time.perf_counter()
        # keep_unresolved: a segment still over budget after the refinement's last round is kept and
        # named in the warnings: a job that ends with a mesh and says where it is off the budget,
        # rather than with no mesh
        sampler = RingSampler(
            mesh,
            topo,
            pool,
            segment_length=params.segment_length,
            chord_error=params.chord_error,
            keep_unresolved=True,
        )
        tris, tstats = tessellate_solid(sampler, helper=helper)
        unresolved += sampler.unresolved
        timings["tessellate"] = timings.get("tessellate", 0.0) + time.perf_counter() - t
        all_tris.append(tris)
        for k, v in tstats.items():
            stats[k] = stats.get(k, 0) + v
        sampling_totals.add(sampler.stats)
    stats.update(asdict(sampling_totals))

    report("checking mesh", 0.95)
    vertices = pool.xyz.copy()
    vertex_plane = pool.plane.copy()
    triangles = np.concatenate(all_tris)
    vertices[:, 2] -= zmin
    ring = vertex_plane >= 0
    # exactly the float32 height the section was computed at (and that the STL will hold)
    vertices[ring, 2] = planes.section_z[vertex_plane[ring]]
    try:
        volume = check_mesh(vertices, triangles)
    except TessellationError:
        # open edges can be T-junctions (``split_t_junctions``): judged on the exact points, before
        # the rings were put on their float32 planes
        triangles, split = split_t_junctions(pool.xyz, triangles, C.T_JUNCTION_TOL_MM)
        if not split:
            raise
        volume = check_mesh(vertices, triangles)
        stats["t_junctions"] = split
    # the mesh as an STL reader reads it: vertices with equal float32 coordinates are one
    stats["float32_merged_vertices"] = stats["float32_collapsed_triangles"] = 0
    stats["float32_fold_merges"], stats["float32_fold_move_mm"] = 0, 0.0
    welded = weld_float32(vertices, triangles, vertex_plane, planes.z32)
    if welded is not None:
        w_vertices, w_triangles, w_plane, merged, collapsed = welded
        try:
            w_volume = check_mesh(w_vertices, w_triangles)
        except TessellationError as exc:
            # a ring folding back on itself within the float32 rounding: the fold merged away
            unfolded = unfold_float32(vertices, triangles, vertex_plane, planes.z32)
            u_volume = None if unfolded is None else _closed_volume(*unfolded[0][:2])
            if unfolded is None or u_volume is None:
                warnings.append(
                    touching_contour_warning(w_triangles, w_plane, planes.z, collapsed)
                    if edge_defects(w_triangles, len(w_vertices))[1]
                    else f"the mesh as an STL reader reads it (vertices with equal float32 coordinates merged) "
                    f"fails its check ({exc}); the mesh as built (and its 3MF, whose vertices are indexed) is "
                    "closed"
                )
            else:
                (vertices, triangles, vertex_plane, merged, collapsed), folds, moved = unfolded
                volume = u_volume
                stats["float32_merged_vertices"], stats["float32_collapsed_triangles"] = merged, collapsed
                stats["float32_fold_merges"], stats["float32_fold_move_mm"] = folds, moved
        else:
            vertices, triangles, vertex_plane, volume = w_vertices, w_triangles, w_plane, w_volume
            stats["float32_merged_vertices"], stats["float32_collapsed_triangles"] = merged, collapsed
    # points the sampling pooled that no triangle uses (the soap box's 4: crossings solved to place
    # a neighbouring one, and a helper's share's) are not part of the mesh; its 3MF, which is
    # indexed, would carry them
    kept, triangles = drop_unreferenced(triangles, len(vertices))
    stats["unreferenced_vertices_dropped"] = len(vertices) - len(kept)
    vertices, vertex_plane = vertices[kept], vertex_plane[kept]
    warnings.extend(simplification_warnings(params))
    if stats["tangent_segments"]:
        warnings.append(
            f"{stats['tangent_segments']} ring segment(s) are kept over budget where a plane is tangent to "
            "the surface (the section there degenerates to a line or a point)"
        )
    if stats["tolerance_gaps"]:
        warnings.append(
            f"{stats['tolerance_gaps']} ring segment(s), up to {stats['max_gap_mm']:.3g} mm long, exceed the "
            "segment budget because no exact point could be placed between their ends (a plane nearly "
            "tangent to the surface, or a face and its edge disagreeing within the file's tolerance); "
            f"the longest at z = {planes.z[stats['max_gap_plane']]:.4f} mm, {stats['max_gap_at']}"
        )
    if stats["unchecked_segments"]:
        warnings.append(
            f"{stats['unchecked_segments']} ring segment(s) could not be checked against the chord budget: "
            "no exact point of the section could be placed between their ends (a feature smaller than "
            "the topology mesh, or a face whose parametrisation has a pole there); the deviation report "
            "measures them"
        )
    if unresolved:
        warnings.append(unresolved_segments_warning(unresolved, planes.z, params.chord_error))
    for j in sorted(flat_planes):
        warnings.append(
            f"a flat face lies on slicing plane {j} (z = {planes.z[j]:.4f} mm): the exact section there is an "
            "area, and slicers disagree on it (Cura keeps the outline above the face, PrusaSlicer the one "
            "below); the DST mesh gives that plane one outline, the one just below the face (PrusaSlicer's), "
            "and joins it straight to the next plane's ring: what a slicer sees at the planes is exact, the "
            "volume between these two planes is not"
        )
    stats["flat_planes"] = sorted(flat_planes)
    stats["unresolved_planes"] = sorted({j for j, _ in unresolved})
    stats["triangles"] = len(triangles)
    stats["vertices"] = len(vertices)
    stats["ring_vertices"] = int((vertex_plane >= 0).sum())
    stats["mesh_volume_mm3"] = volume
    timings["total"] = time.perf_counter() - t0
    stats["timings_s"] = {k: round(v, 4) for k, v in timings.items()}
    report("done", 1.0)
    return DstMesh(
        vertices=vertices,
        triangles=triangles,
        vertex_plane=vertex_plane,
        planes=planes,
        z_offset=zmin,
        part=part,
        params=params,
        warnings=warnings,
        stats=stats,
    )


def float32_vertices(vertices: np.ndarray, vertex_plane: np.ndarray, z32: np.ndarray) -> np.ndarray:
    """(V, 3) float32 as written to STL; ring vertices' z exactly their plane's ``z32``."""
    v = vertices.astype(np.float32)
    ring = vertex_plane >= 0
    v[ring, 2] = z32[vertex_plane[ring]]
    return v


def weld_float32(
    vertices: np.ndarray, triangles: np.ndarray, vertex_plane: np.ndarray, z32: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int] | None:
    """The mesh as an STL reader reads it: vertices whose float32 coordinates are equal merged
    into the first of them (in the mesh's order) and the triangles that then repeat a corner
    dropped (in the file, facets of zero area). Exact section points micrometres apart along a
    ring can round to one float32 point (r103ec: 25 vertices, 50 triangles; trj4_k1_top-pe-214:
    64 and 128). Returns (vertices, triangles, vertex_plane, merged, dropped), or None where no
    two vertices are equal in float32 (or a ring vertex equals another plane's or a free one)."""
    _, group, n_groups = _float32_groups(vertices, vertex_plane, z32)
    if n_groups == len(vertices) or group is None:
        return None
    return _merged(vertices, triangles, vertex_plane, group, n_groups)


def _float32_groups(
    vertices: np.ndarray, vertex_plane: np.ndarray, z32: np.ndarray
) -> tuple[np.ndarray, np.ndarray | None, int]:
    """The vertices as float32 (as written), each one's group of equal float32 points (None where
    a group holds ring vertices of two planes, or a ring vertex and a free one) and the group count."""
    v32 = float32_vertices(vertices, vertex_plane, z32)
    _, group = merge_equal_vertices(v32)
    n_groups = int(group.max()) + 1 if len(group) else 0
    lo = np.full(n_groups, np.iinfo(np.int64).max)
    hi = np.full(n_groups, np.iinfo(np.int64).min)
    np.minimum.at(lo, group, vertex_plane)
    np.maximum.at(hi, group, vertex_plane)
    return v32, group if (lo == hi).all() else None, n_groups


def _merged(
    vertices: np.ndarray, triangles: np.ndarray, vertex_plane: np.ndarray, group: np.ndarray, n_groups: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int]:
    """Each group's vertices merged into its first, the triangles that then repeat a corner dropped."""
    first = np.full(n_groups, len(vertices))
    np.minimum.at(first, group, np.arange(len(vertices)))
    kept = np.sort(first)
    rank = np.empty(n_groups, dtype=np.int64)
    rank[np.argsort(first)] = np.arange(n_groups)
    t = rank[group][triangles]
    collapsed = repeated_corner(t)
    return vertices[kept], t[~collapsed], vertex_plane[kept], len(vertices) - n_groups, int(collapsed.sum())


def unfold_float32(
    vertices: np.ndarray, triangles: np.ndarray, vertex_plane: np.ndarray, z32: np.ndarray
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray, int, int], int, float] | None:
    """``weld_float32`` where its merge leaves edges of more than two triangles because a ring folds
    back on itself within the float32 rounding: bug27693_cornetta at z = 42.1 runs into a corner,
    turns back 2.6 um and out again (60 exact points within 25 um), so the STL's ring goes through
    float32 points A B C B A B C. The float32 points such an edge joins, ring points of one plane
    at most ``FOLD_ULPS`` float32 steps apart, are merged too (round by round, until no edge of
    more than two triangles is left): the ring passes there once. None where such edges are left
    and none is that short and along one plane (rings of two solids, or two stretches of a ring,
    touching over a length), or where a merge would move a vertex farther than ``FOLD_ULPS``
    float32 steps. Returns the welded mesh (as ``weld_float32``), the number of merges beyond
    equal float32 points and the largest distance (mm) a vertex moved."""
    v32, group, n_groups = _float32_groups(vertices, vertex_plane, z32)
    if group is None:
        return None
    plane_of = np.full(n_groups, -1, dtype=np.int64)
    plane_of[group] = vertex_plane
    reach = FOLD_ULPS * np.spacing(np.abs(v32).max(axis=1)).astype(np.float64)  # per vertex
    point = np.zeros((n_groups, 3))
    point[group] = v32
    step = np.zeros(n_groups)
    step[group] = reach
    joins = np.zeros((0, 2), dtype=np.int64)
    comp = np.arange(n_groups)
    for _ in range(FOLD_ROUNDS):
        g = comp[group]
        t = g[triangles]
        ga, gb = crowded_edges(t[~repeated_corner(t)], n_groups)
        if not len(ga):
            break
        # a fold's own edges: ring points of one plane a few float32 steps apart (the edges from its
        # points to the next plane's or a free vertex, or across a cap, are doubled too: they go
        # once the fold does)
        along = (plane_of[ga] >= 0) & (plane_of[ga] == plane_of[gb])
        along &= np.abs(point[ga] - point[gb]).max(axis=1) <= step[ga]
        if not along.any():
            return None
        joins = np.concatenate([joins, np.column_stack([ga[along], gb[along]])])
        graph = coo_matrix((np.ones(len(joins)), (joins[:, 0], joins[:, 1])), shape=(n_groups, n_groups))
        label = connected_components(graph, directed=False)[1]
        rep = np.full(n_groups, n_groups)
        np.minimum.at(rep, label, np.arange(n_groups))
        comp = rep[label]  # each group's component, named by its first group
    else:
        return None
    g = comp[group]
    _, g = np.unique(g, return_inverse=True)
    n_comp = int(g.max()) + 1
    first = np.full(n_comp, len(vertices))
    np.minimum.at(first, g, np.arange(len(vertices)))
    move = np.linalg.norm(vertices - vertices[first[g]], axis=1)
    if (move > reach).any():
        return None
    extra = n_groups - n_comp
    return _merged(vertices, triangles, vertex_plane, g, n_comp), extra, float(move.max())


def touching_contour_warning(
    triangles: np.ndarray, vertex_plane: np.ndarray, planes_z: np.ndarray, collapsed: int
) -> str:
    """The warning for a mesh that is closed as built but would not be once its equal float32
    vertices were merged (``weld_float32``'s ``triangles`` and ``vertex_plane``; ``collapsed``: the
    facets of zero area it dropped): edges of four triangles where rings touch."""
    a, b = crowded_edges(triangles, len(vertex_plane))
    ends = np.concatenate([a, b])
    named = unique_ints(vertex_plane[ends][vertex_plane[ends] >= 0])
    shown = ", ".join(f"{planes_z[j]:.4f}" for j in named[:10]) + (", ..." if len(named) > 10 else "")
    return (
        f"at {len(named)} plane(s) (z = {shown} mm) ring vertices lie within the float32 rounding of each "
        "other (~1e-5 mm), as where the section touches itself or two solids touch: an STL reader, which "
        f"merges vertices with equal float32 coordinates, gets {len(a)} edge(s) of four triangles "
        f"there (the contour touching itself) and {collapsed} facet(s) of zero area. The mesh is kept as "
        "built, closed (its 3MF, whose vertices are indexed, keeps them apart)"
    )


def _topomesh_or_finer(topomesh: Callable[..., TopoMesh], solid, deflection: float) -> TopoMesh:
    """``topomesh(solid)``, or where BRepMesh's mesh fails (a face left unmeshed, or the mesh not
    closed), the first mesh that does not at ``TOPO_RETRY_FINER`` times the deflection (else the
    first error). BRepMesh's failures can depend on the deflection alone: bug32596_abc_0_13 turned
    (-96.6, 92.7, -126.9) has its face 5 (a narrow B-spline strip) unmeshed at 0.01395-0.01397 mm
    and meshed at 0.01398; from 0.5 to 1.45 times that deflection in steps of 0.05, 6 of 20 meshes
    fail (0.55, 0.8, 1.0, 1.2, 1.25, 1.35). A finer topology mesh only costs time."""
    try:
        return topomesh(solid)
    except TessellationError as exc:
        for factor in C.TOPO_RETRY_FINER:
            try:
                return topomesh(solid, deflection=factor * deflection)
            except TessellationError:
                continue  # the next factor
        raise exc from None


def unresolved_segments_warning(
    unresolved: list[tuple[int, float]], planes_z: np.ndarray, chord: float
) -> str:
    """The warning for ring segments still over the chord budget after the refinement's last round
    (``RingSampler.unresolved``: (plane, length) each)."""
    named, j, longest = unresolved_summary(unresolved)
    shown = ", ".join(f"{planes_z[i]:.4f}" for i in named[:10]) + (", ..." if len(named) > 10 else "")
    return (
        f"{len(unresolved)} ring segment(s) at {len(named)} plane(s) (z = {shown} mm) still failed the "
        f"{chord:g} mm chord check after the refinement's last round (every point solved between their "
        "ends landing off the curve: where a face and its edges disagree by the file's tolerance, or the "
        f"section is not a smooth curve); the longest, {longest:.3g} mm, at z = {planes_z[j]:.4f} mm. Each "
        "is kept between its two exact end points, where the ring may be off the section by more than "
        "the chord target; the deviation report measures it"
    )


def simplification_warnings(params: SliceParams) -> list[str]:
    """Slicers simplify contours again after slicing: a finer chord target does not reach the G-code."""
    out = []
    if params.chord_error < C.CURA_MAX_DEVIATION_MM:
        out.append(
            f"chord_error {params.chord_error} mm is below Cura's own simplification "
            f"(meshfix_maximum_deviation {C.CURA_MAX_DEVIATION_MM} mm, meshfix_maximum_resolution "
            f"{C.CURA_MAX_RESOLUTION_MM} mm): lower those in Cura or the finer rings are simplified away"
        )
    if params.chord_error < C.PRUSA_GCODE_RESOLUTION_MM:
        out.append(
            f"chord_error {params.chord_error} mm is below PrusaSlicer's gcode_resolution "
            f"({C.PRUSA_GCODE_RESOLUTION_MM} mm): lower it or the finer rings are simplified away"
        )
    return out


def estimated_triangles(topo, params: SliceParams) -> float:
    """Lower bound of the DST triangle count: two per ring vertex at the segment budget."""
    if not len(topo.succ):
        return 0.0
    length = float(np.linalg.norm(topo.cross_xyz[topo.succ] - topo.cross_xyz, axis=1).sum())
    return 2.0 * length / (params.segment_length * C.SEGMENT_FILL)


def topo_deflection(diag: float) -> float:
    """BRepMesh deflection (mm) of the topology mesh of a part with this bounding-box diagonal."""
    return min(C.TOPO_DEFLECTION_MAX_MM, max(C.TOPO_DEFLECTION_MIN_MM, C.TOPO_DEFLECTION_REL * diag))


def build_deflection(diag: float, params: SliceParams) -> float:
    """The DST build's topology mesh deflection (mm), and the precision it repairs a solid to."""
    return min(topo_deflection(diag), params.chord_error)


def bbox_diagonal(part: LoadedPart) -> tuple[float, float]:
    """Diagonal and height (mm) of the part's loose, fast bounding box: scale for relative tolerances."""
    box = Bnd_Box()
    BRepBndLib.Add_s(part.compound, box, False)
    lo, hi = np.array(box.CornerMin().Coord()), np.array(box.CornerMax().Coord())
    return float(np.linalg.norm(hi - lo)), float(hi[2] - lo[2])


def _closed_volume(v: np.ndarray, t: np.ndarray) -> float | None:
    """``check_mesh``'s volume, or None where the mesh fails it."""
    try:
        return check_mesh(v, t)
    except TessellationError:
        return None


def check_mesh(v: np.ndarray, t: np.ndarray) -> float:
    """Raise TessellationError unless the mesh is a closed, outward-oriented 2-manifold without
    zero-area faces; return its volume (mm^3)."""
    if len(t) == 0:
        raise TessellationError("the mesh is empty")
    open_edges, dup = edge_defects(t, len(v))
    area2 = np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
    zero = int((area2 <= 1e-18).sum())
    if open_edges or dup or zero:
        raise TessellationError(
            f"mesh check failed: {open_edges} open edges, {dup} non-manifold edges, {zero} zero-area triangles"
        )
    volume = signed_volume(v, t)
    if not math.isfinite(volume) or volume <= 0:
        raise TessellationError("mesh check failed: the mesh is inside out")
    return volume
