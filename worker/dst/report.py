"""The deviation report: DST and conventional meshes cut at the slicer's planes, against the exact B-rep.

``build_report`` is the whole computation: the exact reference and the conventional baselines (in
helpers), then each mesh measured (``measure``) in plane ranges shared among helpers; the JSON
contract is the pydantic model ``Report`` in ``report_schema`` (``Report.model_json_schema()``
documents it). Every mesh is measured as its STL holds it (float32 coordinates) and as a slicer
places it (lowest vertex dropped to z = 0, x and y unchanged).
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass, replace

import numpy as np
from OCP.Bnd import Bnd_Box
from OCP.BRep import BRep_Tool
from OCP.BRepBndLib import BRepBndLib
from OCP.BRepMesh import BRepMesh_IncrementalMesh
from OCP.BRepTools import BRepTools
from OCP.StlAPI import StlAPI_Writer
from OCP.TopAbs import TopAbs_FACE
from OCP.TopExp import TopExp_Explorer
from OCP.TopLoc import TopLoc_Location
from OCP.TopoDS import TopoDS

from worker.dst.baselines import BASELINE_PRESETS, DEFAULT_BASELINES, Preset, parse_baselines
from worker.dst.deviation import DENSE_SPACING_MM
from worker.dst.errors import DstError, ResourceLimitExceeded, TessellationError, UnmeshedFaceError
from worker.dst.forked import Task, TaskDied, TaskGroup
from worker.dst.measure import (
    Measured,
    MeshInput,
    Placed,
    below_reference,
    measure_pieces,
    mesh_report,
    on_bed,
    plane_costs,
    plane_ranges,
    ratios,
    reference_segments,
)
from worker.dst.meshops import repeated_corner
from worker.dst.params import SliceParams
from worker.dst.pipeline import (
    DstMesh,
    bbox_diagonal,
    build_deflection,
    simplification_warnings,
    slice_part,
    topo_deflection,
)
from worker.dst.planes import plan_planes
from worker.dst.reference import ExactSections, closed_length, exact_sections
from worker.dst.report_schema import InputInfo, ReferenceInfo, Report
from worker.dst.report_warnings import (
    edge_tolerance_warning,
    mesh_warnings,
    placement_warnings,
    reference_fault_warning,
    reference_gap_warnings,
    reference_needle_warning,
    self_crossing_warnings,
    unresolved_reference_warning,
)
from worker.dst.step_io import LoadedPart, heal_wires, occt_version, orient, read_step
from worker.dst.stl_io import binary_stl_corners, merge_equal_vertices

Progress = Callable[[str, float], None]


# the exact reference: much finer than any mesh it judges
REFERENCE_CHORD_MM = 1e-3
REFERENCE_SEGMENT_MM = 2.0
# How the report's distances are computed (``deviation.compare``), stated in every report
DISTANCES = (
    "to the exact section curves as the reference models them between its points (each span the curve "
    "through its two ends whose curvature runs linearly between the curvatures at its ends, each taken "
    "from the circle through that point and its neighbours; a span between two section corners, or whose "
    "curve would bow farther than the reference's chord from it, straight). The nearest span of a "
    f"point's plane is found exactly: a k-d tree over points every {DENSE_SPACING_MM} mm along the spans "
    "gives candidates, widened until no nearer span can remain, and the distance is to that span's "
    "curve. vertex_dev is the largest distance of the cut's vertices. chord_dev is the larger of two "
    "one-sided maxima: of the cut's vertices and segment midpoints from the reference, and of the "
    "reference's points and its curves' points over their spans' midpoints from the cut polyline, each "
    "span's peak taken from the parabola through its three distances (at most the resolution above the "
    "largest). Only each plane's largest distances are kept, so a point whose distance to the spans or "
    "segments round it (an upper bound) cannot reach its plane's largest is not searched: the maxima "
    "are those of a search from every point. perimeter_err compares the cut polyline's length with the "
    "modelled curves' length. Meshes are cut with a vertex on a plane counting as below it, and a pair "
    "of cut segments between the same two points (the zero-width slit of a valley edge lying on the "
    "plane) is dropped, as slicers do when they clean their polygons"
)
# Cura drops section loops shorter than this (minimum_polygon_circumference default)
CURA_MIN_CIRCUMFERENCE_MM = 1.0
# A measuring helper gets at least this much work (``plane_costs`` units: cut segments, ~3.5 us of
# CPU each; ~0.09 s): less costs more to fork than it saves.
MIN_MEASURE_CHUNK = 25_000
# Niceness of a job's helpers that start beside its DST build: they take the cores it leaves idle.
# (The exact reference niced less than the OCCT helper, as it holds up every mesh's measuring, made
# the hemisphere's job ~0.3 s slower: there the 0.005 mm baseline is the longest chain.)
BACKGROUND_NICE = 10


# --- conventional baselines ------------------------------------------------------------------------
class UnmeshedBaselineError(UnmeshedFaceError):
    """BRepMesh left faces of the part without triangles at a baseline's preset; ``solids``: the
    indices of the solids they belong to."""

    def __init__(self, message: str, solids: tuple[int, ...]):
        super().__init__(message)
        self.solids = solids


def conventional_mesh(
    part: LoadedPart, preset: Preset, *, parallel: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """OCCT's BRepMesh of the part at ``preset``, as a slicer gets it: written by OCCT's STL writer
    and read back (float32 vertices, equal ones merged as an STL reader merges them, triangles
    oriented outward), degenerate triangles dropped. ``parallel``: faces on OCCT's thread pool, as
    slicers mesh them (not in a forked process: see ``forked``); the mesh is the same either way on
    the parts tested (trj7_b1-ec-214 as read: its face 354 left bare at 0.085 mm in under a second
    either way; one run on the pool was seen going on for more than 10 minutes, not reproduced in
    four tries since). (The writer copies the triangulation in C++; node by node through OCP took
    5x as long: 0.2 s for 53k triangles.) Raises UnmeshedBaselineError where BRepMesh leaves a face
    without triangles (the writer would skip it: the mesh would have a hole)."""
    comp = part.compound
    BRepTools.Clean_s(comp)  # otherwise a finer triangulation already on the faces is reused
    BRepMesh_IncrementalMesh(comp, preset.linear, False, preset.angular, parallel)
    try:
        if unmeshed := _unmeshed_faces(part):
            named = "; ".join(
                f"solid {si + 1}: face(s) {', '.join(str(f + 1) for f in fs)}" for si, fs in unmeshed
            )
            raise UnmeshedBaselineError(
                f"OCCT's mesher left {sum(len(fs) for _, fs in unmeshed)} face(s) without triangles ({named})",
                tuple(si for si, _ in unmeshed),
            )
        with tempfile.TemporaryDirectory(prefix="dst-baseline-") as tmp:
            path = os.path.join(tmp, "baseline.stl")
            writer = StlAPI_Writer()
            writer.ASCIIMode = False
            if not writer.Write(comp, path):
                raise TessellationError("OCCT could not write the conventional mesh")
            with open(path, "rb") as fh:
                v, inv = merge_equal_vertices(binary_stl_corners(fh.read()))
    finally:
        BRepTools.Clean_s(comp)
    t = inv.reshape(-1, 3)
    return v.astype(np.float64), t[~repeated_corner(t)]


def _unmeshed_faces(part: LoadedPart) -> list[tuple[int, list[int]]]:
    """(solid, its faces) of the faces that have no triangulation, numbered as the build numbers
    them (from 0, in ``TopExp_Explorer`` order)."""
    out = []
    for si, solid in enumerate(part.solids):
        bare, k = [], 0
        exp = TopExp_Explorer(solid, TopAbs_FACE)
        while exp.More():
            if BRep_Tool.Triangulation_s(TopoDS.Face(exp.Current()), TopLoc_Location()) is None:
                bare.append(k)
            exp.Next()
            k += 1
        if bare:
            out.append((si, bare))
    return out


def _repaired(part: LoadedPart, solids: Sequence[int], precision: float) -> LoadedPart | None:
    """The part with ``solids`` repaired as the DST build repairs a solid OCCT cannot mesh
    (``heal_wires`` to the build's deflection); None where the repair changes none of them."""
    out, changed = list(part.solids), False
    for si in solids:
        if (healed := heal_wires(part.solids[si], precision)) is not None:
            out[si], changed = healed[0], True
    return replace(part, solids=out) if changed else None


@dataclass
class BaselineLeftOut:
    """A baseline OCCT could not make (``_occt_side``), and why."""

    name: str
    reason: str


@dataclass
class OcctSide:
    """What the report needs from OCCT besides the exact sections and the baselines."""

    xy_box: tuple[tuple[float, float], tuple[float, float]]
    volume_mm3: float


def _occt_side(
    part: LoadedPart,
    baselines: Sequence[str],
    parallel: bool,
    exact: bool = True,
    params: SliceParams | None = None,
) -> Generator[MeshInput | BaselineLeftOut, None, OcctSide | None]:
    """The conventional baseline meshes, each yielded as soon as it is made, the coarsest (quickest)
    first: in a helper, the report measures them while OCCT makes the finer ones. Returns the part's
    exact x/y extent and its exact volume (``exact``; else None).

    Where BRepMesh leaves a face without triangles at a preset (BRepMesh's failures depend on the
    deflection: trj7_b1-ec-214, as read, has its face 354 unmeshed at the paper's presets, and at
    the PrusaSlicer preset on one thread does not finish in minutes), the part is repaired as the
    DST build with ``params`` repairs such a solid (to the build's deflection): that baseline and the
    finer ones after it are meshes of the repaired part, and say so (``MeshInput.repaired``). If the
    repair changes nothing or does not help, the baseline is left out (``BaselineLeftOut``): the
    report goes on with the other meshes."""
    used, why = part, None  # why: where the file as read failed, once the repaired part is used
    # A mesh made on one thread is timed by its CPU seconds, what it takes on a core of its own: in a
    # job the helper making it waits for a core beside the DST build (niced), and its wall time said
    # 0.16 s for the hemisphere's 0.03 s occt_fast mesh. On OCCT's thread pool: its wall time.
    clock = time.perf_counter if parallel else time.process_time
    for name in sorted(baselines, key=lambda n: -BASELINE_PRESETS[n].linear):
        preset = BASELINE_PRESETS[name]
        t = clock()
        try:
            v, tr = conventional_mesh(used, preset, parallel=parallel)
        except UnmeshedBaselineError as exc:
            fixed = None
            if params is not None and used is part:
                fixed = _repaired(part, exc.solids, build_deflection(bbox_diagonal(part)[0], params))
            if fixed is None:
                yield BaselineLeftOut(
                    name,
                    f"on the part repaired as the DST build repairs it, {exc}"
                    if used is not part
                    else f"on the file as read, {exc} (where a slicer importing the file with these settings "
                    "gets a mesh with holes), and repairing it as the DST build repairs such a solid changed "
                    "nothing",
                )
                continue
            used = fixed
            why = (
                f"on the file as read, {exc} at {name}'s settings ({preset.linear} mm, {preset.angular} rad), "
                "where a slicer importing the file gets a mesh with holes"
            )
            t = clock()  # the repaired part's mesh
            try:
                v, tr = conventional_mesh(used, preset, parallel=parallel)
            except UnmeshedBaselineError as again:
                yield BaselineLeftOut(
                    name,
                    f"on the file as read, {exc}, and on the part repaired as the DST build repairs it, {again}",
                )
                continue
        yield MeshInput(
            name,
            "baseline",
            v,
            tr,
            clock() - t,
            f"OCCT {occt_version()} BRepMesh, linear {preset.linear} mm, angular {preset.angular} rad: "
            f"{preset.source}"
            + ("" if parallel else " (on one thread: its CPU seconds)")
            + _app_note(preset)
            + (
                "" if why is None else "; of the part repaired as the DST build repairs it (see the warnings)"
            ),
            why,
        )
    return _exact_extent(part) if exact else None


def _not_the_apps_mesh(preset: Preset) -> bool:
    """A slicer's preset meshed here on another OCCT release than the slicer links."""
    return preset.app is not None and preset.app_occt != occt_version()


def _app_note(preset: Preset) -> str:
    """What a slicer preset's mesh is not, where the slicer links another OCCT release."""
    if not _not_the_apps_mesh(preset):
        return ""
    return (
        f"; {preset.app} itself links OCCT {preset.app_occt}, whose mesher makes another mesh from "
        "these parameters"
    )


def slicer_preset_warning(baselines: Sequence[str]) -> str | None:
    """The warning a report carries when it compares with slicer presets made on another OCCT than
    the slicers link: those baselines are the slicers' parameters, not their meshes."""
    other = [n for n in baselines if _not_the_apps_mesh(BASELINE_PRESETS[n])]
    if not other:
        return None
    apps = sorted({f"{BASELINE_PRESETS[n].app} OCCT {BASELINE_PRESETS[n].app_occt}" for n in other})
    return (
        f"baseline(s) {', '.join(other)} are made with those slicers' STEP-import meshing parameters on "
        f"OCCT {occt_version()}, not by the slicers: they link older OCCT releases ({'; '.join(apps)}), "
        "whose mesher makes other meshes from the same parameters, more or less accurate by part (PrusaSlicer "
        "2.5's own largest chord_dev was 30% smaller on a B-spline hemisphere, 43% larger on a freeform "
        "soap box). To measure your slicer's own mesh, export it as STL and run "
        "`dst report part.step mesh.stl`"
    )


def _exact_extent(part: LoadedPart) -> OcctSide:
    return OcctSide(xy_box(part), part.volume_mm3)  # the box: ~0.5 s of OCCT on the soapbox


def _start_occt_side(
    tasks: TaskGroup,
    part: LoadedPart,
    baselines: Sequence[str],
    params: SliceParams,
    nice: int = 0,
    exact: bool = True,
) -> Task:
    """``_occt_side`` as a task of ``tasks`` (OCCT on one thread in a forked helper)."""
    return tasks.submit(_occt_side, part, baselines, not tasks.forked, exact, params, nice=nice)


@dataclass
class _Reference:
    """The exact sections a report measures against, the chord they were sampled to, and the
    seconds they took."""

    sections: ExactSections
    chord: float
    seconds: float


def _exact_reference(
    part: LoadedPart,
    params: SliceParams,
    heights: np.ndarray | None,
    parallel: bool = True,
    helper: bool = True,
) -> _Reference:
    """The report's exact sections at ``heights`` (None: the planes ``params`` give for the part's
    exact height, found by the reference itself), from their own, finer topology mesh. ``parallel``:
    OCCT's thread pool may be used (not in a forked helper); ``helper``: half the sampling in a
    forked helper of its own."""
    t = time.perf_counter()
    diag, _ = bbox_diagonal(part)
    chord = min(REFERENCE_CHORD_MM, 0.1 * params.chord_error)

    def planned(height: float) -> np.ndarray:
        return plan_planes(height=height, params=params).section_z

    sections = exact_sections(
        part,
        planned if heights is None else heights,
        chord=chord,
        segment_length=REFERENCE_SEGMENT_MM,
        deflection=0.5 * topo_deflection(diag),  # finer than the DST build's: its own topology
        repair_precision=build_deflection(diag, params),  # as the build repairs
        parallel=parallel,
        helper=helper,
    )
    return _Reference(sections, chord, time.perf_counter() - t)


def _occt_result(side: Task) -> OcctSide | None:
    return _helper_result(
        side,
        TessellationError,
        "OCCT failed while meshing the conventional baselines: {exc}; the report can be made "
        "without them (baselines 'none')",
    )


def _measured(task: Task) -> list[Measured]:
    # numpy work only: a helper that dies without a word was killed, in practice for memory
    return _helper_result(
        task,
        ResourceLimitExceeded,
        "a helper measuring the meshes died ({exc}), most likely out of memory: measure fewer "
        "baselines, or use fewer helpers (--processes 1, DST_REPORT_PROCESSES=1)",
    )


def _helper_result(task: Task, error: type[DstError], message: str):
    """The task's result; a helper that died becomes ``error`` with ``message`` (``{exc}``: how)."""
    try:
        return task.result()
    except TaskDied as exc:
        raise error(message.format(exc=exc)) from exc


# --- the computation -------------------------------------------------------------------------------
def build_report(
    part: LoadedPart,
    params: SliceParams,
    *,
    file_name: str,
    dst: DstMesh | None = None,
    meshes: Sequence[MeshInput] = (),
    baselines: Sequence[str] = DEFAULT_BASELINES,
    progress: Progress | None = None,
    processes: int | None = None,
) -> Report:
    """Measure ``dst`` (if given), ``meshes`` and the ``baselines`` presets against the exact part,
    turned by ``params.rotation`` (``meshes`` must be in the turned part's coordinates).

    ``processes``: at most this many forked helper processes at a time (default: the usable CPUs;
    1 computes everything in this process, as it also does where fork is unavailable).
    """
    report = progress or (lambda stage, frac: None)
    baselines = parse_baselines(list(baselines))
    part = orient(part, params.rotation)  # as the DST mesh was made (``dst.part`` is turned already)
    with TaskGroup(forked=processes != 1, limit=processes) as tasks:
        return _build_report(
            part,
            params,
            file_name,
            dst,
            meshes,
            baselines,
            tasks,
            _start_occt_side(tasks, part, baselines, params),
            report,
        )


def slice_and_report(
    path: str | os.PathLike[str],
    params: SliceParams,
    *,
    file_name: str | None = None,
    baselines: Sequence[str] = DEFAULT_BASELINES,
    progress: Progress | None = None,
    processes: int | None = None,
    on_mesh: Callable[[DstMesh], None] | None = None,
) -> tuple[DstMesh, Report]:
    """Read ``path``, build its DST mesh and the mesh's report, the report's OCCT work (the
    baselines, the exact box and volume) started in a helper process before the DST build, on the
    core that build leaves idle much of the time. ``on_mesh`` gets the mesh as soon as it is built
    (to write it before the report is done). Progress: the build 0 .. 0.5, the report 0.5 .. 1."""
    report = progress or (lambda stage, frac: None)
    baselines = parse_baselines(list(baselines))
    t0 = time.perf_counter()
    report("reading STEP", 0.0)
    part = orient(read_step(path), params.rotation)  # before the helpers fork with it
    with TaskGroup(forked=processes != 1, limit=processes) as tasks:
        # Forked, beside the build, at a lower priority (the build keeps its core; they take what
        # it leaves idle): the OCCT side, and with a second helper to spare, the exact reference at
        # the planes it plans from its own exact height (the build's, unless the two heights fall
        # on either side of a plane's limit: then it is made again at the build's planes).
        # Inline (nothing to overlap): after the build.
        side = reference = None
        if tasks.forked:
            side = _start_occt_side(tasks, part, baselines, params, nice=BACKGROUND_NICE, exact=False)
            if tasks.limit >= 2:
                reference = tasks.submit(_exact_reference, part, params, None, False, nice=BACKGROUND_NICE)
        as_read = list(part.solids)
        mesh = slice_part(part, params, progress=lambda s, f: report(s, 0.5 * f), t0=t0, helper=tasks.forked)
        if on_mesh is not None:
            on_mesh(mesh)
        if _replaced(as_read, part.solids):
            # The build repaired a solid OCCT could not mesh and built the mesh from the repaired
            # one (``slice_part``): the helpers forked with the file's. The report measures the mesh
            # against the solid it was built from, as a report after the build does: made again.
            for task in (side, reference):
                if task is not None:
                    task.kill()
            side = reference = None
        # the part's exact box and volume here, while the helpers work: the niced OCCT helper would
        # do them last, starved by the measuring (at nice 0) it holds up
        extent = None
        if side is None:
            side = _start_occt_side(tasks, part, baselines, params)
        else:
            extent = _exact_extent(part)
        out = _build_report(
            part,
            params,
            os.fspath(path) if file_name is None else file_name,
            mesh,
            (),
            baselines,
            tasks,
            side,
            lambda s, f: report(s, 0.5 + 0.5 * f),
            reference,
            extent,
        )
    return mesh, out


def _replaced(before: Sequence, after: Sequence) -> bool:
    """Whether any of the solids ``before`` is no longer the one in its place ``after``."""
    return any(not a.IsSame(b) for a, b in zip(before, after, strict=True))


def _build_report(
    part: LoadedPart,
    params: SliceParams,
    file_name: str,
    dst: DstMesh | None,
    meshes: Sequence[MeshInput],
    baselines: tuple[str, ...],
    tasks: TaskGroup,
    side: Task,
    report: Progress,
    reference: Task | None = None,
    extent: OcctSide | None = None,
) -> Report:
    """The report, ``side`` being ``_occt_side``'s task, ``reference`` (if started)
    ``_exact_reference``'s and ``extent`` the part's exact box and volume where the side does not
    compute them. OCCT's own work (the baselines, the exact box and volume) holds the GIL:
    it runs in a child process beside the exact reference, on one thread there (OCCT's thread pool
    stays behind in this process when it forks). The baselines come one by one, each measured as
    soon as it is there while OCCT makes the next (the coarse presets first: their measuring
    overlaps the finer ones' meshing)."""
    warnings: list[str] = []
    report("exact sections", 0.0)
    # plane heights: the DST mesh's own, else planned from the exact height
    dst_heights = None if dst is None else dst.planes.section_z
    made = None
    if reference is not None:
        made = _helper_result(
            reference, TessellationError, "OCCT failed while computing the exact reference sections: {exc}"
        )
        if dst_heights is not None and not np.array_equal(made.sections.heights, dst_heights):
            made = None  # planned for a slightly different exact height: made again at the build's planes
    if made is None:
        # OCCT's thread pool only where no helper meshes a baseline meanwhile: beside one, its threads
        # take turns on the other's core (the hemisphere's topology mesh 0.19 -> 0.24 CPU-s, and the
        # PrusaSlicer preset's mesh beside it 0.76 -> 0.83)
        made = _exact_reference(
            part, params, dst_heights, parallel=not (tasks.forked and baselines), helper=tasks.forked
        )
    ref, chord = made.sections, made.chord
    heights = ref.heights
    t = time.perf_counter()
    planes_z = plan_planes(height=ref.zmax - ref.zmin, params=params).z if dst is None else dst.planes.z
    n_planes = len(heights)
    ref_set, ref_perimeter, loops_exact = reference_segments(ref.loops, ref.corners, chord, n_planes)
    below = below_reference(ref, chord) if ref.flat_planes else None
    ref_seconds = made.seconds + time.perf_counter() - t  # and its segments' search structure

    todo: list[MeshInput] = []
    if dst is not None:
        todo.append(
            MeshInput(
                "dst",
                "dst",
                dst.vertices32.astype(np.float64),
                dst.triangles,
                dst.stats.get("timings_s", {}).get("total"),
                f"DST, segment_length {params.segment_length} mm, chord_error {params.chord_error} mm",
            )
        )
    todo.extend(meshes)
    report("measuring meshes", 0.4)
    # Measured here and in helper processes (``hand_out``): one k-d tree thread each, side by side.
    workers = 1 if tasks.forked and tasks.limit > 1 else -1
    ref_per_plane = np.bincount(ref_set.seg_plane, minlength=n_planes)
    measuring: dict[int, list[tuple[int, Task, int]]] = {}  # per mesh: (first plane, task, piece)

    # Each mesh's plane ranges ("pieces", each a twelfth of a helper's share or less) wait here, largest
    # first. This process measures them one by one (between two, it takes the baselines OCCT has
    # made since), and a core that neither OCCT nor this process uses gets a helper with its part of
    # the waiting work (``hand_out``): while OCCT makes the finer baselines, this process measures
    # on the other core; once it is done, a helper takes about half of what waits. A helper costs a
    # fork and its first touches of the shared memory (the hemisphere's report took ~0.1 CPU-s
    # more with a helper for every core while OCCT worked and this process waited).
    pending: list[tuple[float, MeshInput, int, int]] = []
    placed: dict[int, Placed] = {}  # once per mesh; the helpers share it

    def add(ms: list[MeshInput]) -> None:
        for m in ms:
            placed[id(m)] = Placed(*on_bed(m), heights)
        costs = {id(m): plane_costs(placed[id(m)], ref_per_plane) for m in ms}
        total = sum(float(c.sum()) for c in costs.values())
        n_tasks = max(1, min(tasks.limit, int(total // MIN_MEASURE_CHUNK))) if tasks.forked else 1
        chunk = total / (12 * n_tasks) if n_tasks > 1 else np.inf  # pieces small enough to balance
        pending.extend(
            (float(costs[id(m)][j0:j1].sum()), m, j0, j1)
            for m in ms
            for j0, j1 in plane_ranges(costs[id(m)], chunk)
        )
        pending.sort(key=lambda p: -p[0])

    def measure(share: list[tuple[float, MeshInput, int, int]], forked: bool) -> None:
        args = (
            [(placed[id(m)], j0, j1, m.kind == "dst") for _, m, j0, j1 in share],
            heights,
            ref_set,
            ref_perimeter,
            below,
            n_planes,
            workers,
        )
        if forked:
            task = tasks.submit(measure_pieces, *args)
        else:
            task = Task(measure_pieces, args, False)
        for k, (_, m, j0, _) in enumerate(share):
            measuring.setdefault(id(m), []).append((j0, task, k))

    def hand_out(free: int) -> None:
        # A helper for each core neither OCCT nor this process takes (``free`` tasks could start),
        # with about its part of the waiting work (never less than MIN_MEASURE_CHUNK: a fork costs
        # ~25 ms of CPU); this process takes the rest piece by piece, so the work ends at about the
        # same time everywhere.
        if not tasks.forked or not pending:
            return
        work = sum(p[0] for p in pending)
        helpers = min(free - 1, int(work // MIN_MEASURE_CHUNK) - 1)
        if helpers < 1:
            return
        target = work / (helpers + 1)  # all ending together
        for _ in range(helpers):
            share: list[tuple[float, MeshInput, int, int]] = []
            rest: list[tuple[float, MeshInput, int, int]] = []
            got = 0.0
            for piece in pending:  # largest first, as long as they fit (one left for this process)
                if len(pending) - len(share) > 1 and (not share or got + piece[0] <= target):
                    share.append(piece)
                    got += piece[0]
                else:
                    rest.append(piece)
            pending[:] = rest
            if share:
                measure(share, True)

    left_out: list[BaselineLeftOut] = []

    def kept_meshes(items: list[MeshInput | BaselineLeftOut]) -> list[MeshInput]:
        left_out.extend(m for m in items if isinstance(m, BaselineLeftOut))
        return [m for m in items if isinstance(m, MeshInput)]

    todo.extend(kept_meshes(side.items_ready()))  # the baselines OCCT has made already
    add(todo)
    report("conventional meshes", 0.5)
    while True:
        # free cores first: that reads what OCCT has sent, so a baseline it made just before it
        # ended is among the work handed out with its core, not left to this process alone
        free = tasks.free()
        if arrived := kept_meshes(side.items_ready()):  # the others as OCCT makes them
            todo.extend(arrived)
            add(arrived)
            # again: OCCT's helper may have ended meanwhile (after its last baseline it only takes
            # the part's exact box and volume, the hemisphere's in 3 ms: this process then measured
            # a piece alone before it forked a helper for the other core)
            free = tasks.free()
        hand_out(free)
        if pending:
            measure([pending.pop(0)], False)
        elif side.done() or sum(m.kind == "baseline" for m in todo) + len(left_out) == len(baselines):
            break
        else:
            tasks.wait_any()  # a baseline
    occt = _occt_result(side) or extent
    assert occt is not None  # the side's exact box and volume, or ``extent`` where it made none
    rank = {name: i for i, name in enumerate(baselines)}  # the baselines in the order asked for
    todo.sort(key=lambda m: rank[m.name] if m.kind == "baseline" else -1)
    report("measuring meshes", 0.7)
    measured = {
        id(m): [_measured(t)[k] for _, t, k in sorted(measuring[id(m)], key=lambda r: r[0])] for m in todo
    }
    results = [mesh_report(m, measured[id(m)], planes_z, loops_exact, below) for m in todo]
    exact_volume = occt.volume_mm3
    for r in results:
        r.volume_rel_err = (r.volume_mm3 - exact_volume) / exact_volume if exact_volume > 0 else None

    dst_summary = next((r.summary for r in results if r.kind == "dst"), None)
    if dst_summary is not None:
        for r in results:
            if r.kind != "dst":
                r.ratios = ratios(r.summary, dst_summary)

    # --- warnings ----------------------------------------------------------------------------------
    warnings.extend(part.warnings)
    if slicer_note := slicer_preset_warning(baselines):
        warnings.append(slicer_note)
    warnings.extend(
        f"baseline {m.name} is left out: {m.reason}" for m in sorted(left_out, key=lambda m: rank[m.name])
    )
    repaired_baselines: dict[str, list[str]] = {}  # why -> the baselines made of the repaired part
    for m in todo:
        if m.repaired:
            repaired_baselines.setdefault(m.repaired, []).append(m.name)
    warnings.extend(
        f"baseline(s) {', '.join(names)} are meshes of the part repaired as the DST build repairs it: {why}"
        for why, names in repaired_baselines.items()
    )
    if dst is not None:
        warnings.extend(w for w in dst.warnings if w not in warnings)
    else:
        warnings.extend(simplification_warnings(params))
    for j in ref.flat_planes:
        msg = f"a flat face lies on slicing plane {j} (z = {planes_z[j]:.4f} mm)"
        if not any(w.startswith(msg) for w in warnings):
            warnings.append(msg + ": the exact section there is an area, and slicers disagree on it")
    if ref.flat_planes:
        warnings.append(
            f"the report measures plane(s) {', '.join(map(str, ref.flat_planes))} against the exact outlines "
            "just above and just below the flat face (a few micrometres from the plane), each mesh against "
            "the one its cut matches better (the layer's flat_side says which): a mesh whose cut keeps "
            "either outline is not counted wrong there"
        )
    small = [(j, closed_length(p)) for j, ls in enumerate(ref.loops) for p in ls]
    small = [(j, length) for j, length in small if length < CURA_MIN_CIRCUMFERENCE_MM]
    if small:
        j, length = min(small, key=lambda x: x[1])
        warnings.append(
            f"{len(small)} exact section loop(s) are shorter than {CURA_MIN_CIRCUMFERENCE_MM} mm "
            f"(the smallest, {length:.3g} mm, at z = {planes_z[j]:.4f} mm): Cura drops such loops "
            "(minimum_polygon_circumference), so they will not print whatever the mesh"
        )
    for r in results:
        warnings.extend(mesh_warnings(r))
    for m in todo:
        if m.kind == "dst":
            warnings.extend(
                self_crossing_warnings(
                    [p for piece in measured[id(m)] for p in piece.pockets],
                    planes_z,
                    params.chord_error,
                    ref.loops,
                )
            )
    for m, r in zip(todo, results, strict=True):
        if m.kind == "dst":
            warnings.extend(
                reference_gap_warnings(part, placed[id(m)], r, ref_set, heights, ref.zmin, ref.flat_planes)
            )
    if fault := reference_fault_warning(ref.loops, results, planes_z, params.chord_error, chord):
        warnings.append(fault)
    if needle := reference_needle_warning(ref.loops, results, planes_z, params.chord_error, chord):
        warnings.append(needle)
    for m in todo:
        if m.kind == "dst" and (
            loose := edge_tolerance_warning(
                part,
                placed[id(m)],
                results,
                ref.loops,
                heights,
                ref.zmin,
                planes_z,
                params.chord_error,
                chord,
            )
        ):
            warnings.append(loose)
    if short := unresolved_reference_warning(ref.unresolved, planes_z, chord):
        warnings.append(short)
    warnings.extend(f"solid {i + 1}: {repair}" for i, repair in ref.repairs)
    box_lo, box_hi = occt.xy_box
    warnings.extend(placement_warnings(todo, box_lo, box_hi))

    report("done", 1.0)
    return Report(
        input=InputInfo(
            file=os.path.basename(file_name),
            source_units=sorted(set(part.source_units)),
            solids=len(part.solids),
            bbox_min=(*box_lo, ref.zmin),
            bbox_max=(*box_hi, ref.zmax),
            height_mm=ref.zmax - ref.zmin,
            volume_mm3=exact_volume,
        ),
        params=params,
        planes=[float(z) for z in planes_z],
        reference=ReferenceInfo(
            method=ref.method,
            chord_mm=chord,
            spacing_mm=DENSE_SPACING_MM,
            resolution_mm=chord,
            distances=DISTANCES,
            seconds=round(ref_seconds, 4),
            loops=int(loops_exact.sum()),
        ),
        meshes=results,
        warnings=warnings,
    )


def xy_box(part: LoadedPart) -> tuple[tuple[float, float], tuple[float, float]]:
    """The part's tight x/y extent, mm (from the B-rep, not a mesh)."""
    box = Bnd_Box()
    BRepBndLib.AddOptimal_s(part.compound, box, False, False)
    lo, hi = box.CornerMin().Coord(), box.CornerMax().Coord()
    return (lo[0], lo[1]), (hi[0], hi[1])
