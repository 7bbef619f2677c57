"""Every file of the shared STEP corpus: a checked DST mesh, or a clear, specific error.

A mesh is checked for watertightness, for the slab property (each plane cuts exactly the rings), and
against OCCT's exact section (``BRepAlgoAPI_Section`` with approximation, sampled densely) at three
planes: every ring vertex lies on the exact section, and every exact section point lies within the
chord budget of the ring polylines; and at every plane as the deviation report measures it.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from tests.conftest import CORPUS
from tests.worker.dst.meshcheck import (
    assert_slab_property,
    assert_watertight,
    distance_to_faces,
    occt_section_points,
    ring_edges,
)
from worker.dst.errors import DstError
from worker.dst.params import ROTATION_FIELDS, SliceParams
from worker.dst.pipeline import bbox_diagonal, slice_step, topo_deflection
from worker.dst.reference import closed_length, exact_sections
from worker.dst.report import _exact_reference, build_report
from worker.dst.report_warnings import unresolved_reference_warning
from worker.dst.sampling import RingSampler

pytestmark = pytest.mark.corpus

FILES = (
    sorted(p for p in CORPUS.glob("*/*") if p.suffix.lower() in {".stp", ".step"}) if CORPUS.is_dir() else []
)
MAY_FAIL_DIRS = {"surface", "malformed"}  # these may hold no closed solid: a clear error is right
RING_TOL_MM = 1e-5
SLOW = {
    "tr8_bv1_tc.stp",
    "bug29241.stp",
    "trj3_s1-ec-214.stp",
    "face_recognition_sample_part.stp",
    "trj3_t2-db-214.stp",
    "eight_cyl.stp",
    "box_sides.STEP",
    "11752.stp",
    "bug27453_165-174_piattello.stp",
    "bug32314_corrupted.stp",
    "bug28366_fuselage.stp",
    "as1_motor.step",
    "trj7_b1-ec-214.stp",
    "trj3_s1-al-214.stp",
}

# Files that hold closed solids but on which the core does not yet produce a mesh: kept visible as
# strict xfails (a fix turns them into failures until this list is updated).
KNOWN_FAILURES = {}


# Every plane of every sliced file is measured as the report measures it (``_check_every_plane``): a
# DST ring vertex may be this far from the report's reference (its resolution, 0.001 mm, plus the
# file's own tolerance between faces and edges).
PLANE_VERTEX_TOL_MM = 2e-3
# Files whose DST mesh is off the exact sections at some planes, with what is known of why: the test
# xfails on them while the deviation lasts and fails once it is gone.
KNOWN_PLANE_DEVIATIONS: dict[str, str] = {
    "boxed_sphere.step turned (4.3, 162.2, -128.1)": (
        "z = 2.3: the ring stops 0.05 mm short of a tongue's tip that the reference's points reach (on "
        "the B-rep; OCCT's section stops short too); z = 8.7: the report's reference has a fifth 'loop' "
        "of 0.09 mm, five points there and back along the main loop's curve, which the ring lacks"
    ),
    "trj7_b1-ec-214.stp": (
        "edges with tolerances up to 0.3 mm: faces and their edges disagree by up to 0.28 mm (z = 23.5), "
        "0.06 mm at z = 7.1 and 25.3, so edge roots and face points differ by that much"
    ),
    "bug29241.stp": (
        "z = 266.7 (a flat face on the plane): no exact point beside the face closer than 3e-5 mm to it "
        "(a neighbour's vertex off its plane by the file's tolerance), where a fillet tangent to the face "
        "is 0.011 mm inside the tangent line the ring keeps"
    ),
}

# The report's warning that its reference misses part of a section (a DST ring vertex on the B-rep far
# from it) must name exactly these planes, and appear on no other file. (None since the topology meshes
# get node rows on horizontal ridges: bug27453's plane 87, a sliver 2.5 um below a hole's top line, was
# one.)
REFERENCE_GAPS: dict[str, str] = {}
# Cases whose report's reference is out of order at a plane of the meshes' largest deviations (z of
# the largest pocket, mm): the report names it. (bug27453 had 3500 points within 0.24 mm at z = 37.1
# and 36.9, pockets of 0.0045-0.007 mm^2, until its topology meshes' pole corners took their
# triangles' own u in session 38: ``topomesh._wedge_poles``. trj7 was named at z = 56.9 until session
# 44, where the section ran along x = 155.6143 mm twice, its passes 1e-9 mm apart: no crossing since
# ``REFERENCE_TOUCH_MM``; that was the reference zigzagging across a ridge, one loop since session 52.)
KNOWN_REFERENCE_FAULTS: dict[str, float] = {}


# Parts too large for 0.2 mm layers within the triangle limit, sliced coarser so their geometry is
# still exercised (at 0.2 mm they are refused with resource_limit, which is also a correct answer).
COARSE = {"11752.stp": SliceParams(layer_height=1.0, segment_length=5.0, chord_error=0.05)}


def _params(path: Path) -> SliceParams:
    return COARSE.get(path.name, SliceParams(layer_height=0.2))


def _distance_to_segments(p: np.ndarray, a: np.ndarray, b: np.ndarray, k: int = 8) -> np.ndarray:
    """For each point, the distance (mm, xy) to the nearest of the segments a-b (exactly).

    The segments are cut into pieces no longer than ``h`` (most segments stay whole); candidates are
    the ``k`` pieces with the nearest midpoints (a KD-tree). A piece not among them has its midpoint
    beyond the k-th, so it is at least that far less ``h / 2``: points whose nearest candidate is
    farther than that are asked again with more candidates, and the few still unsure are measured
    against every segment.
    """
    from scipy.spatial import cKDTree

    def to(q: np.ndarray, sa: np.ndarray, sb: np.ndarray) -> np.ndarray:
        ab = sb - sa
        t = np.clip(((q - sa) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-300), 0, 1)
        return np.linalg.norm(q - (sa + t[..., None] * ab), axis=-1).min(axis=-1)

    length = np.linalg.norm(b - a, axis=1)
    h = max(float(np.quantile(length, 0.9)), 1e-9)
    n = np.maximum(np.ceil(length / h).astype(np.int64), 1)
    seg = np.repeat(np.arange(len(a)), n)
    j = np.arange(len(seg)) - np.repeat(np.cumsum(n) - n, n)
    ab = (b - a)[seg]
    pa = a[seg] + (j / n[seg])[:, None] * ab
    pb = a[seg] + ((j + 1) / n[seg])[:, None] * ab
    tree = cKDTree(0.5 * (pa + pb))
    d = np.full(len(p), np.inf)
    todo = np.arange(len(p))
    for kk in (k, 8 * k):
        kk = min(kk, len(pa))
        dk, idx = tree.query(p[todo], k=kk)
        dk, idx = dk.reshape(len(todo), kk), idx.reshape(len(todo), kk)
        d[todo] = to(p[todo][:, None, :], pa[idx], pb[idx])
        if kk == len(pa):
            return d
        todo = todo[d[todo] > dk[:, -1] - 0.5 * h]
        if not len(todo):
            return d
    for i in todo:
        d[i] = to(p[i], a, b)
    return d


def _check_against_exact_sections(mesh) -> None:
    edges, planes = ring_edges(mesh)
    n = len(mesh.planes)
    # a plane with a flat face on it has an area for its exact section, and DST one outline (by
    # design, warned): the nearest plane without one is checked instead
    flat = set(mesh.stats["flat_planes"])
    usable = np.array([j for j in range(n) if j not in flat])
    for j in sorted({int(usable[np.abs(usable - k).argmin()]) for k in (n // 4, n // 2, (3 * n) // 4)}):
        sel = planes == j
        if not sel.any():
            continue
        zw = mesh.z_offset + float(mesh.planes.section_z[j])
        exact = np.concatenate([occt_section_points(s, zw) for s in mesh.part.solids])[:, :2]
        if len(exact) == 0:
            continue
        a = mesh.vertices[edges[sel, 0], :2]
        b = mesh.vertices[edges[sel, 1], :2]
        # exact -> rings: within the chord budget (plus the sampler's own resolution)
        d = _distance_to_segments(exact, a, b)
        assert np.quantile(d, 0.999) <= mesh.params.chord_error + 1e-3, (
            f"plane {j}: exact section far from rings"
        )
        # rings -> exact: each ring vertex is on the exact section
        ring_v = np.unique(edges[sel].ravel())
        from scipy.spatial import cKDTree

        dv, _ = cKDTree(exact).query(mesh.vertices[ring_v, :2])  # exact points are 0.02 mm apart
        # OCCT's section can come back incomplete on B-spline files (DST.md section 7): a ring vertex
        # far from its samples is measured against the B-rep itself
        far = ring_v[dv > 0.02]
        assert len(far) < 0.05 * len(ring_v), (
            f"plane {j}: {len(far)} ring vertices far from the exact section"
        )
        for vid in far[:: max(1, len(far) // 40)]:
            p = mesh.vertices[vid].copy()
            p[2] = zw
            assert distance_to_faces(p, mesh.part.solids)[0] < RING_TOL_MM, (
                f"plane {j}: ring vertex off the B-rep"
            )


def _case(p: Path):
    marks = []
    if p.name in SLOW:
        marks.append(pytest.mark.slow)
    if p.name in KNOWN_FAILURES:
        marks.append(pytest.mark.xfail(reason=KNOWN_FAILURES[p.name], strict=True, raises=DstError))
    return pytest.param(p, marks=marks, id=f"{p.parent.name}/{p.name}")


# the one case of a parametrised corpus test where the corpus is absent
_NO_CORPUS = [
    pytest.param(
        None, marks=pytest.mark.skip(reason=f"the shared STEP corpus is not beside this checkout ({CORPUS})")
    )
]
_CASES = [_case(p) for p in FILES] or _NO_CORPUS


# OCCT's STEP parser has been seen to spin forever (StepData_StepReaderData::SetEntityNumbers) on a
# malformed file in a long-lived test process that had read many other files, while the same file
# reads in 2 s in a fresh process. The service runs every job in a fresh process with a time limit;
# the malformed files are tested the same way, through the command line, so that such a hang cannot
# stall the suite and its cause stays visible.
ISOLATED_DIRS = {"malformed"}
ISOLATED_TIMEOUT_S = 300


def _slice_in_fresh_process(path: Path, tmp: Path) -> None:
    out = tmp / "out.stl"
    try:
        res = subprocess.run(
            [sys.executable, "-m", "worker.cli", "slice", str(path), "-o", str(out), "-q"],
            capture_output=True,
            text=True,
            timeout=ISOLATED_TIMEOUT_S,
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"dst slice did not finish within {ISOLATED_TIMEOUT_S} s on {path.name} (OCCT hang?)")
    if res.returncode == 0:
        mesh = trimesh.load(out, file_type="stl")
        assert mesh.is_watertight and mesh.volume > 0
        return
    assert res.returncode == 1, res.stderr
    last = res.stderr.strip().splitlines()[-1]
    assert last.startswith("dst: error [") and not last.startswith("dst: error [dst_error]"), last


@pytest.mark.parametrize("path", _CASES)
def test_corpus_file(path: Path, tmp_path):
    if path.parent.name in ISOLATED_DIRS:
        _slice_in_fresh_process(path, tmp_path)
        return
    try:
        mesh = slice_step(path, _params(path))
    except DstError as exc:
        assert exc.code != "dst_error" and str(exc), "errors must be specific"
        if path.parent.name in MAY_FAIL_DIRS or exc.code == "resource_limit":
            return
        raise
    assert_watertight(mesh)
    _assert_closed_as_an_stl_reader_reads_it(mesh)
    # every vertex is a triangle's (its 3MF is indexed: a point no triangle uses would be in it)
    assert np.bincount(mesh.triangles.ravel(), minlength=len(mesh.vertices)).all()
    assert_slab_property(mesh)
    # no segment left over budget by the refinement's last round (kept, with a warning, not fatal)
    assert mesh.stats["unresolved_segments"] == 0, mesh.warnings
    assert mesh.vertices[:, 2].min() == 0.0
    vol = mesh.stats["mesh_volume_mm3"] / mesh.part.volume_mm3
    assert 0.97 < vol < 1.03, f"volume ratio {vol}"
    _check_against_exact_sections(mesh)
    _check_every_plane(mesh, path)


def _assert_closed_as_an_stl_reader_reads_it(mesh) -> None:
    """The STL's corners, equal float32 points merged as a slicer merges them: no facet of zero area
    (a repeated corner) and a closed 2-manifold, except where the build warns that rings touch
    within the float32 rounding (trj7 at six planes; trj3_s1-al, whose five solids touch): there it says how many edges of four triangles and facets of zero
    area a slicer gets, and those are the counts. No open edge either way."""
    from worker.dst.meshops import repeated_corner
    from worker.dst.stl_io import merge_equal_vertices

    v, inv = merge_equal_vertices(mesh.vertices32[mesh.triangles].reshape(-1, 3))
    t = inv.reshape(-1, 3)
    zero = repeated_corner(t)
    t = t[~zero]
    a, b = t.ravel(), t[:, [1, 2, 0]].ravel()
    _, uses = np.unique(np.minimum(a, b) * len(v) + np.maximum(a, b), return_counts=True)
    assert (uses % 2 == 0).all(), "open edges"
    touching = [w for w in mesh.warnings if "ring vertices lie within the float32 rounding" in w]
    if not touching:
        assert not zero.any() and (uses == 2).all(), (int(zero.sum()), int((uses > 2).sum()))
        return
    (note,) = touching
    assert f"gets {int((uses > 2).sum())} edge(s) of four triangles" in note, note
    assert f"and {int(zero.sum())} facet(s) of zero area" in note, note


def _check_every_plane(mesh, path: Path, key: str | None = None) -> None:
    """Every plane, measured as the deviation report measures it (its own exact reference, from a
    finer topology mesh, sampled to 0.001 mm): the DST cut's vertices on the exact section, the cut
    within the chord budget of it both ways, as many loops as the exact section. Files with known
    deviations must still show them (a fix makes the test fail until the entry is removed)."""
    report = build_report(mesh.part, mesh.params, file_name=str(path), dst=mesh, baselines=())
    (dst,) = report.meshes
    resolution = report.reference.resolution_mm
    bad = []
    for layer in dst.layers:
        if (layer.loops_exact or layer.loops) and (layer.vertex_dev is None or layer.chord_dev is None):
            bad.append(f"z = {layer.z:.4f}: {layer.loops} loops cut, {layer.loops_exact} exact")
        elif layer.vertex_dev is not None and layer.vertex_dev > PLANE_VERTEX_TOL_MM:
            bad.append(f"z = {layer.z:.4f}: vertex_dev {layer.vertex_dev:.4g} mm")
        elif layer.chord_dev is not None and layer.chord_dev > mesh.params.chord_error + resolution + 1e-6:
            bad.append(f"z = {layer.z:.4f}: chord_dev {layer.chord_dev:.4g} mm")
        elif layer.loops + layer.open_chains != layer.loops_exact:
            bad.append(f"z = {layer.z:.4f}: {layer.loops} loops cut, {layer.loops_exact} exact")
    # no contour crossing itself round a pocket (trj4 once wound a 2.3 mm hole three times at z = 1.3:
    # pockets of 0.35 mm^2 that no per-layer deviation showed; the bow ties left, of points out of
    # order by micrometres, have none)
    assert not [w for w in report.warnings if "crosses itself" in w], report.warnings
    key = key or path.name  # what the KNOWN_... dicts and REFERENCE_GAPS know the case by
    # nor the reference out of order where the meshes' largest deviations are (but where it is known)
    faults = [w for w in report.warnings if "exact reference is out of order" in w]
    if key in KNOWN_REFERENCE_FAULTS:
        assert len(faults) == 1 and f"at z = {KNOWN_REFERENCE_FAULTS[key]:.4f} mm" in faults[0], faults
    else:
        assert not faults, faults
    gaps = [w for w in report.warnings if "reference misses part of the section" in w]
    if key in REFERENCE_GAPS:
        assert len(gaps) == 1 and REFERENCE_GAPS[key] in gaps[0], gaps
    else:
        assert not gaps, gaps
    known = KNOWN_PLANE_DEVIATIONS.get(key)
    if known is None:
        assert not bad, f"{len(bad)} of {len(dst.layers)} planes: " + "; ".join(bad[:8])
        return
    assert bad, f"{key} now passes at every plane: remove it from KNOWN_PLANE_DEVIATIONS"
    pytest.xfail(f"{known} ({len(bad)} planes, e.g. {bad[0]})")


def _turned(name: str, turn: tuple[float, float, float]) -> tuple[Path, SliceParams]:
    """The corpus file ``name`` (under the corpus folder) and its test parameters turned by
    ``turn``; the test is skipped where the corpus is not beside this checkout."""
    path = CORPUS / name
    if not path.is_file():
        pytest.skip(f"the shared STEP corpus is not beside this checkout ({CORPUS})")
    return path, _params(path).model_copy(update=dict(zip(ROTATION_FIELDS, turn, strict=True)))


def _reference_at(mesh, heights: np.ndarray):
    """The report's exact reference (1 um chord, its own finer topology) of the mesh's part at
    ``heights`` alone."""
    diag, _ = bbox_diagonal(mesh.part)
    return exact_sections(
        mesh.part,
        heights,
        chord=1e-3,
        segment_length=2.0,
        deflection=0.5 * topo_deflection(diag),
        helper=False,
    )


@pytest.mark.slow
def test_a_tongue_beyond_a_pinned_loops_crossings_is_sampled_round_its_tip():
    """r103ec turned to (35.3, -158.7, -40.5): at z = 52.5 and 54.3 the plane grazes a tilted crest
    and the section has a narrow tongue (0.27 mm wide) whose tip the coarse topology mesh does not
    reach, in a loop whose crossings are pinned (the kept triangles use them). At z = 52.5 a crossing
    whose root lay at the tip, between its neighbours on either side, was walked down one side past
    the next crossing (the reordering meant for long triangles across a ridge); at z = 54.3 the
    segment round the tip, seeded across the tongue, zigzagged between its sides, and re-sampling it
    piece by piece kept the zigzag. The ring crossed itself round 0.08 mm^2 (chord_dev 0.124 and
    0.084 mm; the last known self-crossing until session 24), and the tangle's segments were
    reported as gaps of the B-rep. Now the root is kept (it lies on the curve between its
    neighbours) and the segment is traced whole round the tip: both planes within budget, no
    crossing, no gap."""
    path, params = _turned("mechanical/r103ec.stp", (35.3, -158.7, -40.5))
    mesh = slice_step(path, params)
    assert mesh.stats["excursions"] > 0
    assert mesh.stats["tolerance_gaps"] == 0, mesh.stats["max_gap_at"]
    assert not [w for w in mesh.warnings if "exceed the" in w], mesh.warnings
    report = build_report(mesh.part, params, file_name=path.name, dst=mesh, baselines=())
    for z in (52.5, 54.3):
        (layer,) = [layer for layer in report.meshes[0].layers if abs(layer.z - z) < 1e-6]
        assert layer.loops == layer.loops_exact == 2, layer
        assert layer.chord_dev <= params.chord_error + report.reference.resolution_mm, layer
        assert layer.vertex_dev <= PLANE_VERTEX_TOL_MM, layer
        assert layer.perimeter_err < 1e-3, layer
    assert not [w for w in report.warnings if "crosses itself" in w], report.warnings


@pytest.mark.parametrize("turn", [(-47.0, -178.7, 118.8), (122.2, -174.3, -59.3)], ids=str)
def test_a_periodic_faces_lowest_point_search_stays_on_a_period_occt_evaluates(turn):
    """bug24595_281390 turned: the search for a periodic B-spline face's lowest point (L-BFGS, not
    bounded by the seam, so that it may cross it). Turned (-47.0, -178.7, 118.8) it tried a step of
    so many periods that OCCT refused to evaluate the surface there ("Geom_BSplineSurface::
    PeriodicNormalization: Vparameter is too great number"); turned (122.2, -174.3, -59.3) (a
    random-turn scan, seed 2525) a line search ran 23 periods out and L-BFGS-B's next point was NaN
    ("cannot convert float NaN to integer"): both jobs failed. The search is evaluated on the period
    nearest its start and bounded to a period either side of it; the part is sliced, and its height
    is the exact one (OCCT's distances from planes above and below it)."""
    path, params = _turned("freeform/bug24595_281390.stp", turn)
    mesh = slice_step(path, params)
    assert_watertight(mesh)
    assert_slab_property(mesh)
    assert 0.97 < mesh.stats["mesh_volume_mm3"] / mesh.part.volume_mm3 < 1.03
    lowest, highest = _exact_z_extent(mesh.part.compound, mesh.z_offset)
    assert abs(mesh.z_offset - lowest) < 1e-6
    assert abs(mesh.stats["height_mm"] - (highest - lowest)) < 1e-6


def _exact_z_extent(shape, near: float, reach: float = 1000.0) -> tuple[float, float]:
    """The exact lowest and highest z of ``shape``: its distances (BRepExtrema) from horizontal
    square faces ``reach`` below and above ``near``."""
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace
    from OCP.BRepExtrema import BRepExtrema_DistShapeShape
    from OCP.gp import gp_Dir, gp_Pln, gp_Pnt

    def gap(z: float) -> float:
        face = BRepBuilderAPI_MakeFace(gp_Pln(gp_Pnt(0, 0, z), gp_Dir(0, 0, 1)), -1e4, 1e4, -1e4, 1e4).Face()
        dist = BRepExtrema_DistShapeShape(shape, face)
        assert dist.IsDone()
        return dist.Value()

    return near - reach + gap(near - reach), near + reach - gap(near + reach)


# Turned cases with a crossing beside an edge whose curve on the face lies off the edge (the node's
# stored (u, v) on the other side of the plane from the node), with the plane (z above the lowest
# point) where it mattered and what it did before the crossing was solved between the nodes' own
# (u, v): Newton from between the stored ones found nothing, or a point out of order.
OFF_EDGE_CURVES = {
    # (a random-turn scan, seed 23) an edge of tolerance 0.003 mm whose curve on its B-spline face
    # lies 0.37 mm from it: the job failed ("no exact point of face 6 at z=137.8408 mm")
    ("trj3_s1-al-214.stp", (78.4, 32.6, -18.9)): (None, "the job failed"),
    # (seed 7) a strip of triangles folded over beside a nearly horizontal flat face: the contour
    # crossed itself (a known self-crossing until session 22)
    ("boxed_sphere.step", (44.0, 176.0, -102.5)): (7.9, "the contour crossed itself"),
}


@pytest.mark.slow
@pytest.mark.parametrize(("name", "turn"), list(OFF_EDGE_CURVES), ids=lambda x: str(x))
def test_a_crossing_beside_an_edge_whose_curve_on_the_face_is_off_the_edge_is_solved(name, turn):
    """A node on a B-rep edge carries the (u, v) of the edge's curve on the face, which a sloppy
    file can put farther from the node than the edge's tolerance says: a topology edge from it across
    a plane then has stored ends that do not bracket the plane. Its crossing is solved between the
    nodes' own (u, v) (projected): the part is sliced, watertight, every triangle between two planes,
    and (where the report is quick) the plane measures within budget with no self-crossing."""
    (path,) = [p for p in FILES if p.name == name] or [None]
    if path is None:
        pytest.skip(f"the shared STEP corpus is not beside this checkout ({CORPUS})")
    params = _params(path).model_copy(update=dict(zip(ROTATION_FIELDS, turn, strict=True)))
    mesh = slice_step(path, params)
    assert_watertight(mesh)
    assert_slab_property(mesh)
    assert 0.97 < mesh.stats["mesh_volume_mm3"] / mesh.part.volume_mm3 < 1.03
    z, _ = OFF_EDGE_CURVES[(name, turn)]
    if z is None:  # (the report of trj3's 795,000 triangles takes a minute)
        return
    report = build_report(mesh.part, params, file_name=path.name, dst=mesh, baselines=())
    (layer,) = [layer for layer in report.meshes[0].layers if abs(layer.z - z) < 1e-6]
    assert layer.loops == layer.loops_exact
    assert layer.chord_dev <= params.chord_error + report.reference.resolution_mm, layer
    assert not [w for w in report.warnings if "crosses itself" in w], report.warnings


# Random turns where a plane grazes a face near a critical point of its height and the coarse
# topology mesh's section had the wrong loops there (z above the lowest point, what the plane
# measured before the grazed topology edges were split: ``ridges.split_grazed_edges``).
GRAZED_PLANES = {
    # (seed 23) a 0.5 mm wide channel: its tip a separate loop, the ring across its neck
    ("r103ec.stp", (51.3, -114.5, -115.7)): (38.7, "chord_dev 0.76 mm, 2 loops of 1"),
    # (seed 23) two loops nearly touching at a saddle on a B-rep edge, joined into one
    ("r103ec.stp", (-63.6, 113.7, -109.6)): (42.9, "chord_dev 0.24 mm, 1 loop of 2"),
    # (seed 7) a saddle 0.0067 mm above the plane: the ring joined the branches the wrong way round
    # (a known self-crossing until session 23)
    ("bug24595_281390.stp", (45.0, 143.0, 99.2)): (85.5, "chord_dev 0.45 mm, 1 loop of 2, a 3.8 mm^2 pocket"),
    # (seed 7) a tongue where the plane grazes a crest, its ring folded over (a known self-crossing
    # until session 23)
    ("r103ec.stp", (-63.7, -125.9, 113.9)): (155.7, "chord_dev 0.33 mm, a 0.107 mm^2 pocket"),
}


@pytest.mark.slow
@pytest.mark.parametrize(("name", "turn"), list(GRAZED_PLANES), ids=lambda x: str(x))
def test_a_plane_grazing_a_face_near_a_critical_point_has_the_exact_loops(name, turn):
    """Topology edges with both ends on one side of the plane while the B-rep between them passes
    it are split there, so the section has the exact loops: the plane measures within budget with
    the reference's loop count, and the contour does not cross itself."""
    (path,) = [p for p in FILES if p.name == name] or [None]
    if path is None:
        pytest.skip(f"the shared STEP corpus is not beside this checkout ({CORPUS})")
    params = _params(path).model_copy(update=dict(zip(ROTATION_FIELDS, turn, strict=True)))
    mesh = slice_step(path, params)
    assert mesh.stats["grazed_nodes"] > 0
    report = build_report(mesh.part, params, file_name=path.name, dst=mesh, baselines=())
    z, _ = GRAZED_PLANES[(name, turn)]
    (layer,) = [layer for layer in report.meshes[0].layers if abs(layer.z - z) < 1e-6]
    assert layer.loops == layer.loops_exact
    assert layer.chord_dev <= params.chord_error + report.reference.resolution_mm, layer
    assert layer.perimeter_err < 1e-3, layer
    assert not [w for w in report.warnings if "crosses itself" in w], report.warnings


@pytest.mark.slow
def test_report_reference_follows_the_curve_where_its_crossings_come_out_of_order():
    """boxed_sphere turned to (4.3, 162.2, -128.1): planes nearly tangent to rounded edges, where the
    report's finer topology mesh gave crossings in an order the reference did not untangle (a loop
    fanning back and forth 340 times over a 0.2 mm bend; a stretch ending on a face's extension past
    its edge, out of the trace's reach). The report overstated the ring's chord_dev up to 0.055 mm
    (OCCT's section: 0.024) and told of parts of the section its reference missed. Those planes now
    measure within the budget and the reference's resolution, with no such warning (the part's other
    planes: test_corpus_file_turned)."""
    path, params = _turned("assembly/boxed_sphere.step", (4.3, 162.2, -128.1))
    mesh = slice_step(path, params)
    report = build_report(mesh.part, params, file_name=path.name, dst=mesh, baselines=())
    (dst,) = report.meshes
    budget = params.chord_error + report.reference.resolution_mm + 1e-6
    for j in (1, 10, 14, 23, 62):  # (chord_dev was 0.052, 0.055, 0.052, 0.052, 0.055 mm)
        layer = dst.layers[j]
        assert layer.chord_dev <= budget and layer.vertex_dev <= PLANE_VERTEX_TOL_MM, (j, layer)
        assert layer.perimeter_err < 0.01, (j, layer)
    assert not [w for w in report.warnings if "reference misses part of the section" in w], report.warnings


def _exact_points_from_ring(mesh, heights: np.ndarray, ref=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every exact point of the report's reference at ``heights`` (above the part's lowest point),
    its distance from the DST mesh's cut there (its STL's float32 vertices, placed as a slicer
    places them) and the index of its plane among ``heights``: (distances, planes, points).
    ``ref``: that reference's ``ExactSections`` if already made (else made here)."""
    from worker.dst.cuts import cut_mesh
    from worker.dst.deviation import SegmentSet
    from worker.dst.measure import MeshInput, on_bed
    from worker.dst.report import _exact_reference

    if ref is None:
        ref = _exact_reference(mesh.part, mesh.params, heights, helper=False).sections
    v, tr = on_bed(MeshInput("dst", "dst", mesh.vertices32, mesh.triangles, None, ""))
    cut = cut_mesh(v, tr, heights)
    pts = np.concatenate([p for ls in ref.loops for p in ls])
    plane = np.concatenate([np.full(len(p), j) for j, ls in enumerate(ref.loops) for p in ls])
    return SegmentSet(cut.seg, cut.seg_plane).distance(pts, plane), plane, pts


def _assert_planes_within_budget(mesh, *z: float) -> tuple[np.ndarray, np.ndarray]:
    """Every exact point of the report's reference at the planes at heights ``z`` (mm above the bed)
    is within the chord budget of the DST mesh's cut there (float32 slack only). Returns the
    points and their distances."""
    (js,) = np.nonzero(np.isclose(mesh.planes.z[:, None], z).any(axis=1))
    assert len(js) == len(z)
    d, plane, pts = _exact_points_from_ring(mesh, mesh.planes.section_z[js])
    worst = int(np.argmax(d))
    assert d[worst] <= mesh.params.chord_error + 1e-6, (mesh.planes.z[js[plane[worst]]], d[worst], pts[worst])
    return pts, d


@pytest.mark.slow
def test_off_centre_bends_are_within_budget_and_a_loose_files_offsets_are_put_down_to_it():
    """boxed_sphere turned to (16.7, -95.9, 65.9). Two segments' curves peaked off their middles
    (z = 8.9: a bend tightening towards the segment's end corner; z = 10.9: across a small lobe),
    where the parabola through the sampled distances is low: exact points of the curve lay 0.0251
    and 0.0257 mm from the ring, over the 0.025 budget (the report's chord_dev, within its 1 um
    resolution, did not show it as a failure). Every exact point of the report's reference is now
    within the budget of the ring (float32 slack only). And at four planes the ring's vertices lie
    on a face 2-6 um from the reference, within that face's 0.059 mm edge tolerance: the report
    says the file is exact only to its tolerances there, and names no gap of its reference. (Five
    before session 36: at plane 7 the ring and the reference now take the same point,
    where the face's curve crosses its trim, ``RunRefiner._into_trim``.)"""
    path, params = _turned("assembly/boxed_sphere.step", (16.7, -95.9, 65.9))
    mesh = slice_step(path, params)
    d, plane, _ = _exact_points_from_ring(mesh, mesh.planes.section_z)
    worst = int(np.argmax(d))
    assert d[worst] <= params.chord_error + 1e-6, (mesh.planes.z[plane[worst]], d[worst])

    report = build_report(mesh.part, params, file_name=path.name, dst=mesh, baselines=())
    assert not [w for w in report.warnings if "reference misses part of the section" in w], report.warnings
    (loose,) = [w for w in report.warnings if "exact only to its tolerances" in w]
    assert "at 4 plane(s) (8, 12, 43, 47;" in loose, loose


@pytest.mark.slow
def test_dst_over_a_budget_finer_than_the_files_edge_tolerances_is_named_where_an_edge_explains_it():
    """boxed_sphere turned (22.6, 70.6, -54.5) at chord_error 0.005 mm (0.4 mm segments), z = 9.1:
    face 127's section ends at its own boundary 18 um from edge 561, whose tolerance is 0.055 mm,
    and the face beyond it begins at the edge's crossing; the ring joins that crossing straight
    from the face's curve and passes 0.0156 mm from the section's end (the part between lies
    34 um off every face: the file joins its faces there only within the edge's tolerance). Every
    ring vertex is on the reference (vertex_dev within the budget); the report names each plane
    where DST is over its budget only at such points, with the edge's tolerance. (Found by
    ``scan_turns.py --seed 3904 --chord-error 0.005 --segment-length 0.4``, which counts such a
    turn as within budget but for the file's edge tolerances.)"""
    from worker.dst.report_warnings import edge_tolerances

    path, params = _turned("assembly/boxed_sphere.step", (22.6, 70.6, -54.5))
    params = params.model_copy(update={"chord_error": 0.005, "segment_length": 0.4})
    mesh = slice_step(path, params)
    heights = mesh.planes.section_z
    ref = _exact_reference(mesh.part, mesh.params, heights, helper=False).sections
    d, plane, pts = _exact_points_from_ring(mesh, heights, ref)
    over = d > params.chord_error + 1e-6
    (j,) = np.unique(plane[over])  # one plane over budget, z = 9.1
    assert mesh.planes.z[j] == pytest.approx(9.1)
    xyz = np.column_stack([pts[over], ref.zmin + heights[plane[over]]])
    tol = edge_tolerances(mesh.part, xyz, d[over])
    assert np.all(tol >= d[over]) and tol.max() == pytest.approx(0.0554, abs=5e-4)

    report = build_report(mesh.part, params, file_name=path.name, dst=mesh, baselines=())
    (dst,) = report.meshes
    assert dst.layers[j].chord_dev == pytest.approx(d[over].max(), abs=1e-3)
    assert dst.layers[j].vertex_dev <= params.chord_error
    (note,) = [w for w in report.warnings if "runs within the tolerance of a B-rep edge" in w]
    assert (
        f"at 1 plane(s) only where the exact section runs within the tolerance of a B-rep edge (plane(s) {j};"
        in note
    )
    assert "z = 9.1000 mm, by an edge of tolerance 0.0554 mm" in note


@pytest.mark.slow
def test_a_bend_next_to_a_corner_that_the_end_segments_midpoint_hides_is_split():
    """boxed_sphere turned to (36.3, -159.6, 99.5), z = 8.5: a 0.595 mm ring segment from a corner
    had its midpoint 4 um from its chord (no quarter check below a quarter of the budget), while its
    curve left the corner 0.44 rad off the chord and bent back, 0.0258 mm from it 0.1 mm along, over
    the 0.025 budget. A run's end segment whose curve leaves the corner (by its face's tangent there)
    more steeply than an arc within the budget leaves its chord is checked at its quarter points and
    split (``stats['end_bend_checks']``): every exact point of the report's reference is within the
    budget of the ring."""
    path, params = _turned("assembly/boxed_sphere.step", (36.3, -159.6, 99.5))
    mesh = slice_step(path, params)
    assert mesh.stats["end_bend_checks"] > 0
    d, plane, pts = _exact_points_from_ring(mesh, mesh.planes.section_z)
    worst = int(np.argmax(d))
    assert d[worst] <= params.chord_error + 1e-6, (mesh.planes.z[plane[worst]], d[worst], pts[worst])


@pytest.mark.slow
def test_a_corner_off_its_faces_curve_is_joined_to_the_curve_where_it_comes_nearest():
    """bug24595_281390 turned to (157.5, -47.8, -129.9), z = 95.7: a corner lies 5.6 um above face 3
    (within the file's tolerance), whose surface rises 0.16 there, so the face's section curve runs
    0.035 mm from the corner; the 0.62 mm ring segment from the corner to the next one passed its
    midpoint and quarter checks while the curve lay 0.0348 mm from it (budget 0.025). The curve's
    point nearest such a corner is added next to it (``stats['gap_ends']``): every exact point of
    the plane's section is within the budget of the ring."""
    path, params = _turned("freeform/bug24595_281390.stp", (157.5, -47.8, -129.9))
    mesh = slice_step(path, params)
    assert mesh.stats["gap_ends"] > 0
    _assert_planes_within_budget(mesh, 95.7)


def test_a_corner_whose_faces_curve_comes_nearest_beyond_the_trim_joins_it_at_the_trim():
    """bug24595_281390 turned to (14.5, -140.6, 37.4), z = 103.1: a corner lies 0.030 mm from face
    15's section curve, whose point nearest it lies beyond the face's trim, and the 0.78 mm ring
    segment from the corner passed its checks while the curve lay 0.028 mm from it where it entered
    the face, 0.011 mm further on (budget 0.025). The point where the curve enters the trim is now
    added next to the corner (``stats['trim_entry_points']``): every exact point of the plane is
    within the budget of the ring."""
    path, params = _turned("freeform/bug24595_281390.stp", (14.5, -140.6, 37.4))
    mesh = slice_step(path, params)
    _assert_planes_within_budget(mesh, 103.1)
    assert mesh.stats["trim_entry_points"] > 0


def test_a_trim_entry_is_searched_for_between_the_parameters_newton_found():
    """bug24595_281390 turned to (53.4, -11.0, 47.0), z = 7.5: a corner lies 0.051 mm from face 16's
    section curve (a face of slope 0.08: 4 um off the surface), whose point nearest it lies beyond
    the trim, and the 0.76 mm segment from the corner passed 0.030 mm from the curve where it enters
    the face (budget 0.025). The search for that entry seeded Newton between the two points' (u, v)
    as projections seeded at (0, 0) gave them, another place on the surface: the first seed sent
    Newton 5 mm away and no entry was added. It starts from the (u, v) Newton found for them: every
    exact point of the plane is within the budget of the ring."""
    path, params = _turned("freeform/bug24595_281390.stp", (53.4, -11.0, 47.0))
    mesh = slice_step(path, params)
    _assert_planes_within_budget(mesh, 7.5)


def test_a_curve_that_leaves_its_face_between_two_crossings_is_bridged_from_boundary_to_boundary():
    """boxed_sphere turned to (30.7, 26.2, 59.9), z = 0.1: face 47's section curve leaves the face
    and comes back 0.3 mm further on (its boundary edge, of tolerance 0.055 mm, lies 5.5 um above
    the plane, and the neighbouring face never reaches it). The points sampled out there were
    dropped, and the ring bridged the gap from its last samples inside, 0.027 mm inside the corner
    of the section that the reference keeps. The samples next to the gap now move to where the
    curve crosses the face's boundary (``RunRefiner._trim_borders``): every exact point of the plane
    is within the budget of the ring. (Another ring at that plane runs along face 47's surface
    beyond its trim there, up to 0.025 mm off the B-rep, before and after: open.)"""
    path, params = _turned("assembly/boxed_sphere.step", (30.7, 26.2, 59.9))
    mesh = slice_step(path, params)
    assert mesh.stats["trim_entry_points"] > 0
    _assert_planes_within_budget(mesh, 0.1)


@pytest.mark.slow
def test_corners_off_their_faces_curves_in_a_loose_file_are_joined_within_budget():
    """trj7_b1-ec-214 (edge tolerances up to 0.3 mm) turned to (131.4, -77.1, 167.6): at z = 0.1 and
    141.7 the ring's points piled up beside corners that lie off their faces' curves, and exact
    points of the section lay 0.032 and 0.035 mm from the ring (budget 0.025). With the corners
    joined to their faces' curves where those enter the trim (``RunRefiner._into_trim``), every
    exact point of both planes is within the budget of the ring."""
    path, params = _turned("freeform/trj7_b1-ec-214.stp", (131.4, -77.1, 167.6))
    mesh = slice_step(path, params)
    _assert_planes_within_budget(mesh, 0.1, 141.7)
    assert mesh.stats["trim_entry_points"] > 0


@pytest.fixture(scope="module")
def trj7_turned():
    """trj7_b1-ec-214 turned to (-99.8, 126.0, -162.8) (scan seed 3909) and its DST mesh (~70 s)."""
    path, params = _turned("freeform/trj7_b1-ec-214.stp", (-99.8, 126.0, -162.8))
    return slice_step(path, params)


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="open since session 41: with the part's top a new node, the top plane's section west of "
    "edge node 1355 on face 26 is covered by no run (0.0349 mm from the ring, budget 0.025)",
)
def test_a_bridge_to_a_corner_is_sampled_on_the_corners_other_face(trj7_turned):
    """trj7_b1-ec-214 turned to (-99.8, 126.0, -162.8), z = 259.1 (scan seed 3909), the plane
    8.5 um below the part's top (a dome on face 27, 0.25 mm from its edge with face 26): face 26's
    curve leaves its trim near edge 189 (tolerance 0.014 mm) 0.17 mm before the ring's corner on
    that edge, and the ring bridged from there to the corner. The section between runs on face 25
    and bends 0.031 mm off that bridge (budget 0.025). The bridge is now sampled on face 25 (the
    corner's other face), and every exact point of the plane is within the budget of the ring.

    That was on a topology mesh whose highest node, on the edge of faces 26 and 27, had been moved
    onto the top, dragging face 26's triangles over face 27. Since session 41 the top is a new node
    (``lowest._make_node``) and that edge node, 0.3 um above the plane, is on it: the ring's runs
    either side of it are both on face 27, a handover piles its samples at a spot 0.05 mm from it,
    and the section west of it on face 26 is bridged 0.0349 mm off. (The faces there disagree by
    up to the edge's 0.0136 mm, on a slope of a few percent.) Open: xfail until it is fixed."""
    mesh = trj7_turned
    assert mesh.stats["corner_handovers"] > 0
    _assert_planes_within_budget(mesh, 259.1)


@pytest.mark.slow
def test_a_gap_of_the_brep_is_named_where_the_ring_and_the_reference_bridge_it(trj7_turned):
    """trj7_b1-ec-214 turned to (-99.8, 126.0, -162.8): at six planes the file's faces stop short
    of each other, 0.3-1.6 mm apart, and no face holds the section between them: OCCT's own
    section passes no nearer than 0.05 mm to the middle of the reference's straight bridge across
    each gap. The DST ring follows a face's surface past its trim there, 0.13-0.2 mm from the
    bridge (a job's report read that as DST's max vertex_dev and chord_dev, 0.196 mm, with no word
    why). The report names the gap of the B-rep at those six planes, and no gap of its reference."""
    from types import SimpleNamespace

    from OCP.BRepAlgoAPI import BRepAlgoAPI_Section
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeVertex
    from OCP.BRepExtrema import BRepExtrema_DistShapeShape
    from OCP.gp import gp_Dir, gp_Pln, gp_Pnt

    from worker.dst.cuts import cut_mesh
    from worker.dst.measure import MeshInput, Placed, on_bed, reference_segments
    from worker.dst.report_warnings import reference_gap_warnings

    mesh = trj7_turned
    (js,) = np.nonzero(np.isclose(mesh.planes.z[:, None], (16.9, 40.3, 41.3, 75.1, 78.9, 79.1)).any(axis=1))
    assert len(js) == 6
    heights = mesh.planes.section_z[js]
    ref = _reference_at(mesh, heights)
    ref_set, _, _ = reference_segments(ref.loops, ref.corners, 1e-3, len(js))
    placed = Placed(
        *on_bed(MeshInput("dst", "dst", mesh.vertices32.astype(np.float64), mesh.triangles)), heights
    )
    cut = cut_mesh(placed.vertices, placed.triangles, heights)
    d, span = ref_set.nearest(cut.vertices, cut.vertex_plane)
    found = []  # per plane: the ring's farthest vertex from the reference, the bridge's length, OCCT's gap
    for k in range(len(js)):
        mine = np.flatnonzero(cut.vertex_plane == k)
        far = mine[np.argmax(d[mine])]
        a, b = ref_set.seg[span[far]]
        z = float(ref.zmin + heights[k])
        section = BRepAlgoAPI_Section(
            mesh.part.compound, gp_Pln(gp_Pnt(0.0, 0.0, z), gp_Dir(0.0, 0.0, 1.0)), False
        )
        section.Approximation(True)
        section.Build()
        middle = BRepBuilderAPI_MakeVertex(gp_Pnt(*(0.5 * (a + b)).tolist(), z)).Vertex()
        found.append(
            (d[far], np.linalg.norm(b - a), BRepExtrema_DistShapeShape(middle, section.Shape()).Value())
        )
    found = np.array(found)
    assert ((found[:, 0] > 0.1) & (found[:, 0] < 0.2)).all(), found
    assert ((found[:, 1] > 0.25) & (found[:, 1] < 1.7)).all(), found  # straight bridges across the gaps
    assert (found[:, 2] > 0.05).all(), found  # OCCT's section: no curve there either
    layers = [
        SimpleNamespace(index=k, vertex_dev=float(d[cut.vertex_plane == k].max()), z=float(mesh.planes.z[j]))
        for k, j in enumerate(js.tolist())
    ]
    (warning,) = reference_gap_warnings(
        mesh.part, placed, SimpleNamespace(layers=layers), ref_set, heights, ref.zmin, []
    )
    assert warning.startswith("the B-rep leaves a gap in the section at 6 plane(s) (0, 1, 2, 3, 4, 5;")


@pytest.mark.slow
def test_the_top_made_a_node_leaves_the_faces_beside_it_alone():
    """trj7_b1-ec-214 turned to (32.9, 100.0, -141.2), z = 270.9 (scan seed 4002): the part's top
    (a dome on face 23) lies 1.9 mm from edge 125 to face 373, and the topology mesh's highest node
    was on that edge, 6 um below the top plane. That node was moved onto the top: face 373's
    triangles around it then reached over face 23, the top plane's loop crossed them, and its ring
    bridged 0.0526 mm inside the section (budget 0.025); the report's reference, whose topology
    mesh had the same move, made a corner there and missed the bulge too. The top is now a new
    node: every exact point of the plane is within the budget of the ring."""
    path, params = _turned("freeform/trj7_b1-ec-214.stp", (32.9, 100.0, -141.2))
    mesh = slice_step(path, params)
    _assert_planes_within_budget(mesh, 270.9)


@pytest.mark.slow
def test_report_reference_has_no_points_beyond_a_faces_trim_next_to_a_corner():
    """bug24595_281390 turned to (-119.7, -47.5, -168.3), z = 43.5: at a corner, face 0's surface lies
    off the B-rep edge within the file's tolerance and rises slowly, so its curve at the plane runs
    on past the face's trim. The reference's points there (~100, up to 0.03 mm beyond the trim, on
    the surface's extension) made a tongue that the DST ring rightly lacks, and the report read a
    chord_dev of 0.0323 mm (budget 0.025) there. Points beyond the trim next to a corner are dropped
    up to the first one inside it (``RunRefiner._drop_off_trim_ends``): every reference point near
    that corner lies on the B-rep, and every exact point of the plane is within the budget of the
    ring."""
    path, params = _turned("freeform/bug24595_281390.stp", (-119.7, -47.5, -168.3))
    mesh = slice_step(path, params)
    pts, _ = _assert_planes_within_budget(mesh, 43.5)
    corner = np.array([24.8546, 125.2515])  # where the tongue left the corner (the turned part's x, y)
    near = pts[np.linalg.norm(pts - corner, axis=1) < 0.1]
    assert len(near) >= 2
    (j,) = np.flatnonzero(np.isclose(mesh.planes.z, 43.5))
    z = mesh.z_offset + float(mesh.planes.section_z[j])
    off = distance_to_faces(np.column_stack([near, np.full(len(near), z)]), mesh.part.solids)
    assert off.max() < 1e-4, off.max()


def test_ring_points_next_to_a_corner_lie_inside_their_faces_trim():
    """trj4_k1_top-pe-214 (edge tolerances up to 0.008 mm): next to many corners a face's section runs
    on past the face's trim, and the ring's last points before the corner lay there, up to 0.005 mm
    off the B-rep (40-99 vertices a plane at z = 1.5, 1.7 and 11.1), where the report's reference
    (which drops them) read a vertex_dev of 0.005-0.009 mm. They are dropped in the build too: every
    ring vertex at those planes lies on the B-rep."""
    path, params = _turned("inch/trj4_k1_top-pe-214.stp", (0.0, 0.0, 0.0))
    mesh = slice_step(path, params)
    assert mesh.stats["off_trim_end_points"] > 0
    for z in (1.5, 1.7, 11.1):
        (j,) = np.flatnonzero(np.isclose(mesh.planes.z, z))
        ring = mesh.vertices[mesh.vertex_plane == j] + [0.0, 0.0, mesh.z_offset]
        off = distance_to_faces(ring, mesh.part.solids)
        assert off.max() < 1e-6, (z, off.max())


@pytest.mark.slow
def test_ring_points_off_the_trim_stay_where_the_chord_across_them_would_stray():
    """boxed_sphere turned to (-85.5, 94.7, -31.9), z = 0.3: next to a corner the build's topology
    mesh gives a run the wrong face (a narrow one it missed), and the run's two points lie on that
    face's extension 0.03 mm off the B-rep, 0.023 mm at most from the B-rep's curve. Dropped as
    beyond the trim, they left a chord 0.085 mm off the curve; they stay where the chord across
    them would pass farther than the budget from them: every exact point of the plane is within
    the budget of the ring."""
    path, params = _turned("assembly/boxed_sphere.step", (-85.5, 94.7, -31.9))
    mesh = slice_step(path, params)
    _assert_planes_within_budget(mesh, 0.3)


@pytest.mark.slow
def test_report_reference_keeps_a_segment_it_cannot_resolve_and_says_where():
    """trj7_b1-ec-214 (edge tolerances up to 0.3 mm) turned to (-33.7, -98.1, 159.6), z = 14.1: a
    corner lies 2.6 um off its face's curve, and every point the reference's refinement solved
    between them landed at the curve's end, 2.6 um from the corner. After its last round that
    segment still failed its check at the reference's 0.001 mm, and the whole report failed
    ("section curves cannot meet the chord budget"), leaving a job with its mesh and no report.
    The reference keeps such a segment between its exact ends and records its plane and length
    (``ExactSections.unresolved``), which the report's warnings name."""
    path, params = _turned("freeform/trj7_b1-ec-214.stp", (-33.7, -98.1, 159.6))
    mesh = slice_step(path, params)  # (the part as the build repairs it: BRepMesh hangs on one face)
    (j,) = np.flatnonzero(np.isclose(mesh.planes.z, 14.1))
    ref = _exact_reference(mesh.part, params, heights=mesh.planes.section_z[j - 1 : j + 2]).sections
    assert all(ref.loops), "a plane without its section"
    longest = max(length for _, length in ref.unresolved)
    assert {j for j, _ in ref.unresolved} == {1}, ref.unresolved
    assert len(ref.unresolved) >= 1 and 0.001 < longest < 0.01, ref.unresolved
    note = unresolved_reference_warning(ref.unresolved, mesh.planes.z[j - 1 : j + 2], ref.chord)
    assert note is not None and "z = 14.1000 mm" in note, note


@pytest.mark.slow
def test_quarter_points_the_seed_path_puts_past_their_segment_are_solved_from_its_chord():
    """trj6_k1-al-214 turned to (112.9, 27.5, -64.7), z = 44.5: round a loop 0.5 mm across, the seed
    path put both quarter points of a 0.167 mm segment past its ends, and its midpoint, 0.024 mm
    from the chord, passed with the curve 0.028 mm from it (budget 0.025). Such quarter points are
    solved again from the chord's quarter points (``stats['quarter_resolves']``): every exact point
    of the plane is within the budget of the ring."""
    path, params = _turned("freeform/trj6_k1-al-214.stp", (112.9, 27.5, -64.7))
    mesh = slice_step(path, params)
    assert mesh.stats["quarter_resolves"] > 0
    _assert_planes_within_budget(mesh, 44.5)


@pytest.mark.slow
def test_a_segment_across_a_sharp_tip_is_traced_not_kept_as_a_gap():
    """bug27453_165-174_piattello turned to (89.5, 112.2, -78.9): at z = 14.7, 24.1 and 101.3 the
    topology mesh cuts across a tip of the section 0.37 mm deep, and Newton from seeds either side
    of a watershed lands on either flank, never on the tip: the seed interval closed, and a 1.26 mm
    segment was kept over budget as a gap of the B-rep (no sharp turn of the ring to look at). Such a
    gap between two points inside one face is traced along the face (``_gap_segments``): no gap is
    left, and every exact point at those planes is within the budget of the ring."""
    path, params = _turned("mechanical/bug27453_165-174_piattello.stp", (89.5, 112.2, -78.9))
    mesh = slice_step(path, params)
    assert mesh.stats["tolerance_gaps"] == 0
    _assert_planes_within_budget(mesh, 14.7, 24.1, 101.3)


@pytest.mark.slow
@pytest.mark.parametrize("wedged", [True, False], ids=["poles_wedged", "poles_as_brepmesh_gives_them"])
def test_a_point_newton_put_past_a_pole_of_its_face_is_solved_on_the_face(monkeypatch, wedged):
    """bug27453_165-174_piattello turned to (89.5, 112.2, -78.9), z = 86.5: the plane passes 2 um
    below the apex of a cap of revolution, whose (u, v) box ends at the pole there. Newton put a
    ring point through the pole, 2 um past the box, 3 um from the tip of the section; dropped as
    off the face, it left a 0.25 mm segment 0.036 mm from the tip. It is solved again from its
    parameters mirrored through the pole (``_through_pole``): the point lies on the B-rep, and every
    exact point of the plane is within the budget of the ring. Since the topology mesh's pole
    corners take their triangles' own u (``topomesh._wedge_poles``, session 38) the seeds there lie
    at the right angle and no point goes past the pole; with the corners as BRepMesh gives them
    the case is still there, and ``_through_pole`` still solves it."""
    if not wedged:
        monkeypatch.setattr("worker.dst.topomesh._wedge_poles", lambda *args: None)
    path, params = _turned("mechanical/bug27453_165-174_piattello.stp", (89.5, 112.2, -78.9))
    mesh = slice_step(path, params)
    assert (mesh.stats["pole_points"] == 0) if wedged else (mesh.stats["pole_points"] > 0)
    _assert_planes_within_budget(mesh, 86.5)
    (j,) = np.flatnonzero(np.isclose(mesh.planes.z, 86.5))
    ring = mesh.vertices[mesh.vertex_plane == j] + [0.0, 0.0, mesh.z_offset]
    tip = ring[np.linalg.norm(ring[:, :2] - [-77.7955, -4.1972], axis=1) < 0.01]
    assert len(tip) >= 1
    assert distance_to_faces(tip, mesh.part.solids).max() < 1e-6


@pytest.mark.slow
def test_a_solids_lowest_point_beside_its_rims_seam_vertex_gets_the_plane_above_it():
    """eight_cyl turned to (-147.4, -67.2, -169.1), z = 506.1: one solid of the assembly has its
    lowest point on a closed circular rim, 5.5 um below the plane and 7 um below the rim's lowest
    mesh node, which is the rim's seam vertex. The search for the rim's extreme between that node's
    neighbours skipped it (they straddle the seam), so the node was not snapped onto the exact
    lowest point, and the plane's 1.1 mm sliver of the section was missing from the DST mesh (the
    report's reference, from a finer topology mesh, had it). The two spans either side of the seam
    are searched: the sliver is there, within the budget of every exact point."""
    path, params = _turned("assembly/eight_cyl.stp", (-147.4, -67.2, -169.1))
    mesh = slice_step(path, params)
    _assert_planes_within_budget(mesh, 506.1)


@pytest.mark.slow
def test_a_segment_round_a_deep_bend_is_split_whatever_its_samples_say():
    """Ventilator turned to (-135.2, -164.2, -177.2), first plane (z = 0.1): a 0.117 mm ring segment
    round a ~0.035 mm bend was sampled at 0.022 mm at its midpoint, one of its quarter points landed
    on the curve past the segment's end (saying nothing), and the curve lay 0.032 mm from it against
    the 0.025 budget. A segment whose sampled distance exceeds 0.15 of its length turns through more
    than ~67 degrees and is split (``stats['deep_bends']``): every exact point of the plane's section
    is within the budget of the ring."""
    path, params = _turned("freeform/Ventilator.stp", (-135.2, -164.2, -177.2))
    mesh = slice_step(path, params)
    assert mesh.stats["deep_bends"] > 0
    d, _, pts = _exact_points_from_ring(mesh, mesh.planes.section_z[:1])
    assert d.max() <= params.chord_error + 1e-6, pts[np.argmax(d)]


@pytest.mark.slow
def test_a_segment_whose_quarter_point_is_lost_round_a_tight_bend_is_estimated_from_the_other():
    """Ventilator turned to (105.4, 22.5, -109.3), z = 78.9: a 0.197 mm ring segment round a ~0.19 mm
    bend had its midpoint (placed along the seed path) at t = 0.24 of its chord, 0.0187 mm from it,
    one quarter point past its end and the other at t = 0.62, 0.0242 mm: no parabola, and the
    larger sample passed, while the curve lay 0.0253 mm from the segment near its middle (budget
    0.025). The two samples now give the peak of t (1 - t) g(t) (``zero_end_peak``): every exact
    point of the plane's section is within the budget of the ring."""
    path, params = _turned("freeform/Ventilator.stp", (105.4, 22.5, -109.3))
    mesh = slice_step(path, params)
    _assert_planes_within_budget(mesh, 78.9)


@pytest.mark.slow
def test_a_segment_whose_samples_bunch_at_its_ends_is_sampled_in_between():
    """bug29241 turned to (26.5, -17.6, -116.2), z = 321.3 (1.8 mm layers put a plane there too, at a
    ninth of the build): a 0.276 mm ring segment round a bend of a cone's section had its midpoint,
    placed along the seed path, at t = 0.893 of its chord and its quarter points at 0.035 and 0.929
    (at most 0.010 mm from it), and passed while the curve lay 0.028 mm from it at t = 0.5 (budget
    0.025). A segment whose samples leave more than half its chord unseen is now sampled in the
    middle of that gap (``_gap_sags``): every exact point of the plane is within the budget."""
    path, params = _turned("mechanical/bug29241.stp", (26.5, -17.6, -116.2))
    mesh = slice_step(path, params.model_copy(update={"layer_height": 1.8}))
    assert mesh.stats["gap_samples"] >= 1
    _assert_planes_within_budget(mesh, 321.3)


@pytest.mark.slow
def test_report_reference_keeps_a_tongue_tip_its_trace_between_suspects_would_lose():
    """boxed_sphere turned to (-11.5, -70.9, -79.8): at four planes the reference (sampled to 1 um,
    where the DST build's 25 um accepts longer segments) passed a tongue's tip several times over
    (at z = 0.3, 116 vertices five times across a 0.2 mm tip); the trace between the suspect
    segments would have dropped vertices of the curve beyond its ends, so it was refused and the
    tangle kept. Every mesh's perimeter_err there came from the reference: 0.21, 0.09, 0.05, 0.15
    for DST (12.65 mm of reference for 10.8 of curve at z = 0.3). The run round such a piece is now
    traced from corner to corner: the reference is a little longer than the curve's 25 um polyline
    (inscribed in it) and no longer than the chord budget allows, and the DST perimeters match."""
    path, params = _turned("assembly/boxed_sphere.step", (-11.5, -70.9, -79.8))
    mesh = slice_step(path, params)
    report = build_report(mesh.part, params, file_name=path.name, dst=mesh, baselines=())
    (dst,) = report.meshes
    planes = (1, 2, 41, 64)
    coarse = exact_sections(
        mesh.part,
        mesh.planes.section_z[list(planes)],
        chord=params.chord_error,
        segment_length=params.segment_length,
        deflection=topo_deflection(bbox_diagonal(mesh.part)[0]),
        helper=False,
    )
    for k, j in enumerate(planes):
        assert dst.layers[j].perimeter_err < 0.01, (j, dst.layers[j])
        polyline = sum(closed_length(p) for p in coarse.loops[k])
        reference = polyline * (1.0 + dst.layers[j].perimeter_err)  # DST's cut is that polyline's twin
        assert reference >= polyline - 1e-6, (j, reference, polyline)
        assert reference < 1.005 * polyline, (j, reference, polyline)


@pytest.mark.slow
def test_a_section_that_nearly_pinches_itself_has_both_its_loops_in_the_reference_and_the_ring():
    """bug24595_281390 turned to (150.2, 46.5, 5.1), at z = 87.5: the section nearly pinches itself
    beside an 8 mm tongue (a saddle just off the plane), into two loops. The topology meshes joined
    them: the reference's traces failed there (its loop crossing itself round pockets of square
    millimetres, a spike 3 mm off the curve: every mesh's chord_dev 2.7-2.9 mm, perimeter_err 0.26,
    the summaries' maxima; the report warned that these measured its reference) and the DST ring
    crossed itself round a 2.4 mm^2 pocket. With the grazed topology edges split, both have the two
    loops, and the ring measures within budget with no such pocket and no warning about the
    reference. (Still there: seven ring vertices up to 0.018 mm off the B-rep, on a face's surface
    past its trim, in a strip where the contour turns over, which the report names.)"""
    path, params = _turned("freeform/bug24595_281390.stp", (150.2, 46.5, 5.1))
    mesh = slice_step(path, params)
    report = build_report(mesh.part, params, file_name=path.name, dst=mesh, baselines=())
    (layer,) = [layer for layer in report.meshes[0].layers if abs(layer.z - 87.5) < 1e-6]
    assert layer.loops == layer.loops_exact == 2
    assert layer.chord_dev <= params.chord_error + report.reference.resolution_mm, layer
    assert layer.perimeter_err < 0.005, layer
    assert not [w for w in report.warnings if "exact reference is out of order" in w], report.warnings
    crossings = [w for w in report.warnings if "crosses itself" in w]
    assert all("a strip where the contour turns over" in w for w in crossings), crossings


FANNED_CAPS = {
    # a bowl 0.58 mm across just below the plane, whose topology crossings lay up to 0.25 mm inside
    # its section: the ring folded onto half the curve (chord_dev 0.37 mm)
    ("trj6_k1-al-214.stp", (114.0, 17.7, 173.1)): 16.1,
}


@pytest.mark.slow
@pytest.mark.parametrize(("name", "turn"), list(FANNED_CAPS), ids=lambda x: str(x))
def test_a_small_cap_whose_crossings_lie_deep_inside_its_curve_is_fanned_from_the_traced_curve(name, turn):
    """A small cap (a disk component between two planes bounded by one loop) whose topology
    crossings lie far inside its exact curve: their exact points came out of order and the pinned
    ring folded, the contour crossing itself. Its ring is now traced on the exact curve and the cap
    fanned from its node farthest from the plane: within budget there, no crossing anywhere."""
    (path,) = [p for p in FILES if p.name == name] or [None]
    if path is None:
        pytest.skip(f"the shared STEP corpus is not beside this checkout ({CORPUS})")
    params = _params(path).model_copy(update=dict(zip(ROTATION_FIELDS, turn, strict=True)))
    mesh = slice_step(path, params)
    assert mesh.stats["fanned_caps"] >= 1
    assert_watertight(mesh)
    assert_slab_property(mesh)
    report = build_report(mesh.part, params, file_name=path.name, dst=mesh, baselines=())
    (layer,) = [layer for layer in report.meshes[0].layers if abs(layer.z - FANNED_CAPS[(name, turn)]) < 1e-6]
    assert layer.loops == layer.loops_exact
    assert layer.chord_dev <= params.chord_error, layer
    assert layer.perimeter_err < 0.002, layer
    assert not [w for w in report.warnings if "crosses itself" in w], report.warnings


@pytest.mark.slow
def test_a_small_cap_whose_crossing_was_walked_past_its_neighbour_is_right_without_a_fan(monkeypatch):
    """r103ec turned (-55.5, -11.2, 146.2), at z = 9.5: a small cap whose ring folded and doubled
    part of its loop (perimeter_err 0.0052, a 0.047 mm^2 pocket) and was fanned from the traced
    curve. The fold came from a crossing walked along the curve past its neighbour; with that walk
    refused (``RingSampler._reordered``) the pinned ring is in order: no fan, within budget, no
    crossing. Without the neighbour rule the cap is fanned again: the case still has the fold."""
    path, params = _turned("mechanical/r103ec.stp", (-55.5, -11.2, 146.2))
    with monkeypatch.context() as m:
        m.setattr(RingSampler, "_neighbour_points", lambda self, c: (None, None))
        assert slice_step(path, params).stats["fanned_caps"] >= 1
    mesh = slice_step(path, params)
    assert mesh.stats["fanned_caps"] == 0
    assert_watertight(mesh)
    assert_slab_property(mesh)
    report = build_report(mesh.part, params, file_name=path.name, dst=mesh, baselines=())
    (layer,) = [layer for layer in report.meshes[0].layers if abs(layer.z - 9.5) < 1e-6]
    assert layer.loops == layer.loops_exact
    assert layer.chord_dev <= params.chord_error, layer
    assert layer.perimeter_err < 0.002, layer
    assert not [w for w in report.warnings if "crosses itself" in w], report.warnings


@pytest.mark.slow
@pytest.mark.parametrize("turn", [(-71.7, 8.5, -112.9), (52.3, 4.7, 130.6)])
def test_crossings_at_one_point_are_one_vertex_of_the_ring_and_of_the_triangles_beside_it(turn, monkeypatch):
    """bug29241 turned (-71.7, 8.5, -112.9) at z = 372.3 (and (52.3, 4.7, 130.6) at 293.5 and 293.9):
    the section passes 1e-10 mm from where two topology edges of one triangle cross the plane. The
    ring dropped one of the two points as a repeat, the kept triangles on both sides used both, and
    the build failed its own mesh check (3 and 6 open edges). Such crossings now share one vertex
    (``RingSampler._merge_coincident``). Coarse segments (the crossings, and so the case, are those
    of the default settings) keep the build at ~25 s."""
    # (with the topology mesh's pole corners as BRepMesh gives them: since they are wedged,
    # ``topomesh._wedge_poles``, the first turn's crossings no longer meet at one point)
    monkeypatch.setattr("worker.dst.topomesh._wedge_poles", lambda *args: None)
    path, params = _turned("mechanical/bug29241.stp", turn)
    params = params.model_copy(update={"segment_length": 5.0, "chord_error": 0.1})
    mesh = slice_step(path, params)  # raises TessellationError where the mesh check fails
    assert mesh.stats["merged_crossings"] >= 1
    assert_watertight(mesh)
    assert_slab_property(mesh)


@pytest.mark.slow
def test_samples_of_a_run_at_one_point_are_one_vertex_of_the_ring_and_of_the_triangles_beside_it():
    """bug27453_165-174 turned (22.6, 52.9, -123.0) at chord_error 0.005 mm, z = 20.3: the section
    round a dimple 31 um deep, a curve a few micrometres across, is one pinned segment sampled to
    191 points, two pairs of them 0.4 nm and 8 pm apart. The ring dropped one of each pair as a
    repeat, the kept triangles of the dimple's cap used both, and the build failed its own mesh
    check (6 open edges). A run's samples now drop such repeats before anything uses them
    (``RunRefiner._without_repeats``). (Found by ``scan_turns.py --seed 3903 --chord-error 0.005
    --segment-length 0.4``; the default 0.8 mm segments show it too.)"""
    path, params = _turned("mechanical/bug27453_165-174_piattello.stp", (22.6, 52.9, -123.0))
    params = params.model_copy(update={"chord_error": 0.005})
    mesh = slice_step(path, params)  # raises TessellationError where the mesh check fails
    assert mesh.stats["repeat_samples"] >= 2
    assert_watertight(mesh)
    assert_slab_property(mesh)
    _assert_planes_within_budget(mesh, 20.3)


def test_a_stretch_of_crossings_off_the_trim_collapses_onto_its_two_ends_in_order():
    """trj3_s1-al-214 turned (-123, 47, -18) at 0.15 mm layers: seven crossings in a row round one node at
    z = 92.3 have their roots beyond face 5's trim. Each took the vertex of the nearer end of the
    stretch, and the sixth was nearer the first end than the fifth and the seventh were: the ring
    went A, B, A, B over one edge, and the build failed its mesh check (6 non-manifold edges). The
    first half of the stretch (by length) now takes the first end's vertex, the rest the other's."""
    path, params = _turned("freeform/trj3_s1-al-214.stp", (-123.0, 47.0, -18.0))
    params = params.model_copy(update={"layer_height": 0.15, "segment_length": 2.0, "chord_error": 0.05})
    mesh = slice_step(path, params)  # raises TessellationError where the mesh check fails
    assert mesh.stats["off_trim_crossings"] >= 7
    assert_watertight(mesh)
    assert_slab_property(mesh)
    # (not _check_every_plane: at z = 93.825, the next plane with such a stretch, the report finds the
    # contour turning over in a strip, where the stretches' ends are the same vertices either way)
    _check_against_exact_sections(mesh)


@pytest.mark.slow
def test_a_piece_collapsed_onto_a_line_through_three_points_leaves_no_hole():
    """bug29241 turned (37, -61, 113) at 0.3 mm layers (5 mm segments, 0.2 mm chord): a topology
    triangle's piece above z = 277.05 is a crossing and two nodes on one straight line (2e-12 mm
    off it). The piece was dropped as collapsed, which only closes the mesh for a path there and
    back; here its neighbours hold the long edge and the two short ones, and the build failed its
    mesh check (3 open edges). The neighbour on the long edge is now split at the middle point
    (``split_t_junctions``)."""
    path, params = _turned("mechanical/bug29241.stp", (37.0, -61.0, 113.0))
    params = params.model_copy(update={"layer_height": 0.3, "segment_length": 5.0, "chord_error": 0.2})
    mesh = slice_step(path, params)  # raises TessellationError where the mesh check fails
    assert mesh.stats["t_junctions"] >= 1
    assert_watertight(mesh)
    assert_slab_property(mesh)


@pytest.mark.parametrize(
    ("scale", "failure"), [(1.0, "face 5 could not be meshed"), (1.2, "surface mesh is not closed")]
)
def test_a_solid_brepmesh_fails_on_at_one_deflection_is_meshed_finer(monkeypatch, scale, failure):
    """bug32596_abc_0_13 turned (-96.6, 92.7, -126.9): at the build's topology deflection (0.01397
    mm) BRepMesh gives face 5 no triangles (at 0.01398 it meshes it), and the build failed; at 1.2
    times it (another part's size) its mesh is not closed. The solid is meshed again finer
    (``TOPO_RETRY_FINER``) before anything else: the mesh is closed, sliced and exact."""
    from worker.dst import constants as C
    from worker.dst import pipeline
    from worker.dst.errors import TessellationError
    from worker.dst.step_io import orient, read_step
    from worker.dst.topomesh import build_topomesh

    path, params = _turned("mechanical/bug32596_abc_0_13.step", (-96.6, 92.7, -126.9))
    part = orient(read_step(path), params.rotation)
    diag, _ = pipeline.bbox_diagonal(part)
    deflection = scale * pipeline.topo_deflection(diag)
    with pytest.raises(TessellationError, match=failure):  # the case: OCCT 8.0.1's mesher there
        build_topomesh(
            part.solids[0],
            deflection=deflection,
            angular=C.TOPO_ANGULAR_RAD,
            merge_tol=C.MERGE_TOL_REL * diag,
        )
    topo_deflection = pipeline.topo_deflection
    monkeypatch.setattr(pipeline, "topo_deflection", lambda d: scale * topo_deflection(d))
    mesh = slice_step(path, params)
    assert_watertight(mesh)
    assert_slab_property(mesh)
    assert not [w for w in mesh.warnings if "repaired" in w], mesh.warnings
    _check_against_exact_sections(mesh)
    _check_every_plane(mesh, path, f"{path.name} turned {params.rotation}")


def test_a_face_occt_cannot_mesh_is_closed_and_reported():
    """trj10's face 73 is a planar sliver of 1.3e-9 mm^2 that BRepMesh leaves unmeshed, and a corner
    beside it has node copies 6e-7 mm apart (beyond the merge tolerance, within the file's vertex
    tolerance): the surface is closed there and the user is told. (test_corpus_file checks the mesh
    itself against OCCT's sections.)"""
    path = CORPUS / "mechanical" / "trj10_b2-oc-214.stp"
    if not path.is_file():
        pytest.skip(f"the shared STEP corpus is not beside this checkout ({CORPUS})")
    mesh = slice_step(path, SliceParams(layer_height=0.2))
    assert_watertight(mesh)
    assert any("could not mesh face 73" in w and "sliver" in w for w in mesh.warnings), mesh.warnings
    assert any("node(s) on cracks were merged" in w for w in mesh.warnings), mesh.warnings


# Parts turned to another print orientation: every check of ``test_corpus_file``, on sections the file's
# own orientation never shows (ec_soapbox-A at 35 degrees about y had midpoints of 0.02 mm segments
# land 0.2 mm away on another piece of the section, and was split into 1.5 million segments down to
# 1e-7 mm: 3.2 million triangles, 50 s; bug21802_as1 is an assembly of placed instances).
TURNED = {
    "ec_soapbox-A.stp": (0.0, 35.0, 0.0),
    "bug21802_as1-oc-214.stp": (90.0, 0.0, 30.0),
    # planes nearly tangent to its rounded edges: the report's finer topology gave crossings out of
    # order (a loop fanning 340 times over a 0.2 mm bend, a spur onto a face's extension), which
    # overstated the mesh's chord_dev up to 0.055 mm (0.024 against OCCT's section)
    "boxed_sphere.step": (4.3, 162.2, -128.1),
}


@pytest.mark.slow
@pytest.mark.parametrize(
    "path",
    [pytest.param(p, id=f"{p.parent.name}/{p.name}") for p in FILES if p.name in TURNED] or _NO_CORPUS,
)
def test_corpus_file_turned(path: Path):
    turn = dict(zip(ROTATION_FIELDS, TURNED[path.name], strict=True))
    mesh = slice_step(path, _params(path).model_copy(update=turn))
    assert_watertight(mesh)
    assert_slab_property(mesh)
    vol = mesh.stats["mesh_volume_mm3"] / mesh.part.volume_mm3
    assert 0.97 < vol < 1.03, f"volume ratio {vol}"
    assert not [w for w in mesh.warnings if "exceed the segment budget" in w], mesh.warnings
    # the budget is used, not split away (the turned soapbox once had 16 times its triangles): per
    # plane, about as many triangles as the part has unturned
    unturned = slice_step(path, _params(path))
    per_plane = len(mesh.triangles) / len(mesh.planes)
    assert per_plane < 3.0 * len(unturned.triangles) / len(unturned.planes)
    _check_against_exact_sections(mesh)
    _check_every_plane(mesh, path, f"{path.name} turned {TURNED[path.name]}")


@pytest.mark.slow
def test_a_plane_where_dst_is_over_budget_beside_a_needle_of_the_section_is_named():
    """bug27453_165-174_piattello turned (129.5, 111.3, 134.0): at z = 38.1 the exact section has a
    spike 0.034 mm out and back along itself (its points on the B-rep, its legs under 0.1 um apart),
    which the DST ring does not follow: DST's chord_dev there is the spike's length, over its
    budget. The report names that plane and the needle, and no other (z = 27.5, over budget across a
    gap until the pole fix, had no needle)."""
    path, params = _turned("mechanical/bug27453_165-174_piattello.stp", (129.5, 111.3, 134.0))
    mesh = slice_step(path, params)
    report = build_report(mesh.part, params, file_name=path.name, dst=mesh, baselines=())
    over = {
        round(layer.z, 4): layer.chord_dev
        for layer in report.meshes[0].layers
        if layer.chord_dev is not None
        and layer.chord_dev > params.chord_error + report.reference.resolution_mm
    }
    assert over.keys() == {38.1}, over  # (27.5, over across a gap, is within budget since the pole fix)
    assert over[38.1] == pytest.approx(0.0341, abs=5e-4)
    (note,) = [w for w in report.warnings if "needle" in w]
    assert "at 1 plane(s)" in note and "the longest 0.0342 mm, at z = 38.1000 mm" in note, note


@pytest.mark.slow
def test_a_caps_ring_just_below_its_apex_goes_round_it():
    """bug27453_165-174_piattello turned (-171.8, -177.1, -119.4): at z = 27.1 the plane passes
    0.01 mm below the apex of a cap of revolution (face 242), a section circle 0.036 mm across that
    cuts only the fan of topology triangles round the apex. The crossings of that fan were solved
    along (u, v) edges from the apex's one fixed u and all landed on a 12-degree arc: the ring was
    a sliver along it, 0.0357 mm from the far side of the circle. Every exact point is now within
    the budget (``topomesh._wedge_poles``)."""
    path, params = _turned("mechanical/bug27453_165-174_piattello.stp", (-171.8, -177.1, -119.4))
    mesh = slice_step(path, params)
    _assert_planes_within_budget(mesh, 27.1)


@pytest.mark.slow
def test_reference_repairs_a_solid_occt_cannot_mesh_before_meshing_it_finer(monkeypatch):
    """trj7_b1-ec-214 turned to (-99.8, 126.0, -162.8) as read: OCCT leaves a face unmeshed at the
    reference's 0.01 mm, at 0.014 and at the build's 0.02 (face 354, which the DST build repairs),
    and its next retry, 0.007 mm, ran for more than 15 minutes. The reference of a mesh alone
    (``dst report``: no build repaired the solid) now repairs the solid as the build does before
    any finer mesh, and names the face the build names."""
    from OCP.BRepGProp import BRepGProp
    from OCP.GProp import GProp_GProps

    from worker.dst import reference
    from worker.dst.pipeline import build_deflection
    from worker.dst.step_io import orient, read_step

    path, params = _turned("freeform/trj7_b1-ec-214.stp", (-99.8, 126.0, -162.8))
    part = orient(read_step(path), params.rotation)
    diag, _ = bbox_diagonal(part)
    precision = build_deflection(diag, params)
    real, tried = reference._topomesh, []

    def logged(solid, deflection, diag, parallel=True):
        props = GProp_GProps()
        BRepGProp.VolumeProperties_s(solid, props)
        tried.append((round(deflection, 6), props.Mass()))
        return real(solid, deflection, diag, parallel)

    monkeypatch.setattr(reference, "_topomesh", logged)
    mesh, used, repair = reference._reference_topomesh(
        part.solids[0], 0.5 * precision, diag, False, precision
    )
    assert precision == pytest.approx(0.02)
    assert [d for d, _ in tried] == [0.01, 0.014, 0.02, 0.01] and used == pytest.approx(0.01)
    file_volume, repaired_volume = tried[0][1], tried[-1][1]
    assert all(v == file_volume for _, v in tried[:3]) and repaired_volume != file_volume
    assert repair.startswith("face 354 could not be meshed") and "edges under 0.02 mm dropped" in repair
    assert not mesh.filled_faces


@pytest.mark.slow
def test_the_baselines_of_a_file_the_mesher_leaves_with_a_hole_are_of_its_repair():
    """trj7_b1-ec-214 as read: OCCT's mesher, on one thread (as in the report's helper), leaves its
    face 354 (11.8 mm^2) without triangles at the paper's presets (and at the PrusaSlicer preset runs
    for minutes). ``dst report trj7.stp mesh.stl`` failed on that after minutes of exact sections.
    The baselines are now meshes of the part repaired as the DST build repairs it (its face
    boundaries' gaps closed within 0.02 mm): named as such in their warning, with the face the file
    as read lost, and covering that face (points on it within the preset's deflection and the
    repair's precision of the mesh, where the rest of the B-rep is farther off)."""
    from OCP.BRep import BRep_Builder, BRep_Tool
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeVertex
    from OCP.BRepClass import BRepClass_FaceClassifier
    from OCP.BRepExtrema import BRepExtrema_DistShapeShape
    from OCP.BRepTools import BRepTools
    from OCP.gp import gp_Pnt, gp_Pnt2d
    from OCP.TopAbs import TopAbs_FACE, TopAbs_IN
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS, TopoDS_Compound

    from worker.dst.baselines import BASELINE_PRESETS
    from worker.dst.errors import UnmeshedFaceError
    from worker.dst.report import _occt_side, conventional_mesh
    from worker.dst.step_io import read_step

    path, params = _turned("freeform/trj7_b1-ec-214.stp", (0.0, 0.0, 0.0))
    part = read_step(path)
    with pytest.raises(UnmeshedFaceError, match=r"\(solid 1: face\(s\) 354\)"):
        conventional_mesh(part, BASELINE_PRESETS["occt_fast"], parallel=False)

    # points inside face 354 as read, and their distances to every other face
    others, builder = TopoDS_Compound(), BRep_Builder()
    builder.MakeCompound(others)
    exp, faces = TopExp_Explorer(part.solids[0], TopAbs_FACE), []
    while exp.More():
        faces.append(TopoDS.Face(exp.Current()))
        exp.Next()
    for k, face in enumerate(faces):
        if k != 353:
            builder.Add(others, face)
    face = faces[353]
    surface = BRep_Tool.Surface_s(face)
    u0, u1, v0, v1 = BRepTools.UVBounds_s(face)
    on_face = []
    for u in np.linspace(u0, u1, 9)[1:-1]:
        for v in np.linspace(v0, v1, 9)[1:-1]:
            if BRepClass_FaceClassifier(face, gp_Pnt2d(u, v), 1e-7).State() == TopAbs_IN:
                on_face.append(surface.Value(u, v).Coord())
    assert len(on_face) >= 10
    rest = [
        BRepExtrema_DistShapeShape(BRepBuilderAPI_MakeVertex(gp_Pnt(*p)).Vertex(), others).Value()
        for p in on_face
    ]
    assert max(rest) > 0.3, max(rest)  # a hole there would leave points that far from the mesh

    made = list(_occt_side(part, ["occt_fast", "occt_high_quality"], False, False, params))
    assert [m.name for m in made] == ["occt_fast", "occt_high_quality"]
    for m in made:
        assert m.repaired is not None and "face(s) 354) at occt_fast's settings" in m.repaired, m.repaired
        corners = m.vertices[m.triangles]
        for p in on_face:  # its distance to the triangles within 3 mm
            near = corners[(np.linalg.norm(corners - p, axis=2) < 3.0).any(axis=1)]
            closest = trimesh.triangles.closest_point(near, np.broadcast_to(p, (len(near), 3)))
            dist = np.linalg.norm(closest - p, axis=1).min()
            assert dist < BASELINE_PRESETS[m.name].linear + 0.02, (m.name, p, dist)


@pytest.mark.slow
def test_a_topology_edge_crossing_lower_planes_is_split_where_it_grazes_the_next():
    """trj7_b1-ec-214 as read, its top plane (z = 56.9 above the bed, 0.1 mm under a ridge of face
    42 that stands between two level lines 4.77 mm apart): BRepMesh's triangles there run across
    the ridge, 0.24 mm below it at a deflection of 0.02 mm, their edges from 0.47 mm below the
    plane to 0.005 mm below it, crossing the planes below. ``split_grazed_edges`` looked only at
    edges crossing no plane, so the mesh's cut joined the ridge's two sides: the DST ring and the
    report's reference zigzagged from one level line to the other (DST's cut 2,960 mm, the
    reference's 1,874 mm in three loops), where OCCT's own section is one loop (141.7 mm: the two
    lines and the ridge's ends). Edges crossing planes are now checked too, for the next plane
    beyond their ends, with split points up to a quarter of the edge's length off it along the
    surface's normal (and within the band across it: ``test_ridges``): one loop in both."""
    from OCP.BRepAlgoAPI import BRepAlgoAPI_Section
    from OCP.BRepGProp import BRepGProp
    from OCP.gp import gp_Dir, gp_Pln, gp_Pnt
    from OCP.GProp import GProp_GProps

    from worker.dst.cuts import cut_mesh
    from worker.dst.measure import MeshInput, Placed, on_bed

    path = CORPUS / "freeform/trj7_b1-ec-214.stp"
    if not path.is_file():
        pytest.skip(f"the shared STEP corpus is not beside this checkout ({CORPUS})")
    mesh = slice_step(path, _params(path))
    j = len(mesh.planes.section_z) - 1
    assert abs(float(mesh.planes.z[j]) - 56.9) < 1e-3
    heights = mesh.planes.section_z[j : j + 1]
    section = BRepAlgoAPI_Section(
        mesh.part.compound,
        gp_Pln(gp_Pnt(0.0, 0.0, mesh.z_offset + float(heights[0])), gp_Dir(0.0, 0.0, 1.0)),
        False,
    )
    section.Approximation(True)
    section.Build()
    props = GProp_GProps()
    BRepGProp.LinearProperties_s(section.Shape(), props)
    occt_length = props.Mass()
    assert 141.0 < occt_length < 142.5
    placed = Placed(
        *on_bed(MeshInput("dst", "dst", mesh.vertices32.astype(np.float64), mesh.triangles)), heights
    )
    cut = cut_mesh(placed.vertices, placed.triangles, heights)
    assert cut.loops.tolist() == [1] and cut.open_chains.tolist() == [0]
    cut_length = float(np.linalg.norm(cut.seg[:, 1] - cut.seg[:, 0], axis=1).sum())
    assert abs(cut_length - occt_length) < 0.1  # an inscribed polyline, within the chord budget
    ref = _reference_at(mesh, heights)
    assert len(ref.loops[0]) == 1
    assert abs(closed_length(ref.loops[0][0]) - occt_length) < 0.1
