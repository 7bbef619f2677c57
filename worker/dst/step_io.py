"""Read a STEP file into closed solids in millimetres, with the warnings a user must see.

OCCT's ``STEPControl_Reader`` is used directly (not build123d's ``import_step``, which returns an
empty shape for empty, truncated and non-STEP files). Placements of assembly instances are applied
by ``OneShape``; lengths are converted to millimetres by the reader whatever the file's unit.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from OCP.BRep import BRep_Builder, BRep_Tool
from OCP.BRepAdaptor import BRepAdaptor_Curve
from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeSolid, BRepBuilderAPI_Sewing, BRepBuilderAPI_Transform
from OCP.BRepCheck import BRepCheck_Analyzer
from OCP.BRepGProp import BRepGProp
from OCP.BRepTools import BRepTools_ReShape
from OCP.collections import (
    IndexedDataMap_TopoDS_Shape_List_TopoDS_Shape_TopTools_ShapeMapHasher as ShapeAncestorMap,
)
from OCP.collections import Sequence_TCollection_AsciiString
from OCP.gp import gp_Pnt, gp_Trsf
from OCP.GProp import GProp_GProps
from OCP.IFSelect import IFSelect_ReturnStatus
from OCP.ShapeFix import ShapeFix_Solid, ShapeFix_Wireframe
from OCP.STEPControl import STEPControl_Reader
from OCP.TopAbs import (
    TopAbs_EDGE,
    TopAbs_FACE,
    TopAbs_FORWARD,
    TopAbs_REVERSED,
    TopAbs_SHELL,
    TopAbs_SOLID,
    TopAbs_VERTEX,
)
from OCP.TopExp import TopExp, TopExp_Explorer
from OCP.TopoDS import TopoDS, TopoDS_Compound, TopoDS_Edge, TopoDS_Shape, TopoDS_Solid, TopoDS_Vertex
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial.distance import pdist

from worker.dst.errors import EmptyGeometryError, NotASolidError, StepReadError
from worker.dst.sniff import SNIFF_BYTES, sniff_step

SEWING_TOL_MM = 1e-3  # gaps up to 1 um between open shells' edges are closed by sewing
# Corners farther apart than this that one vertex joins (a file's coarse tolerance) are split apart
LOOSE_VERTEX_GAP_MM = 0.05
VERTEX_MIN_TOL_MM = 1e-7  # OCCT's Precision::Confusion()
HEAL_VOLUME_REL = 1e-4  # a repair of face boundaries may change the solid's volume by this much at most

NO_ROTATION = (0.0, 0.0, 0.0)


@dataclass
class LoadedPart:
    """Closed solids read from one STEP file, all in millimetres and in the file's placement."""

    solids: list[TopoDS_Solid]
    source_units: list[str]
    warnings: list[str] = field(default_factory=list)
    sewn: bool = False
    # degrees about the fixed x, y and z axes, in that order, applied to the file's geometry (``orient``)
    rotation: tuple[float, float, float] = NO_ROTATION

    @property
    def compound(self) -> TopoDS_Compound:
        """All solids in one compound (for bounding boxes and whole-part queries)."""
        comp = TopoDS_Compound()
        builder = BRep_Builder()
        builder.MakeCompound(comp)
        for s in self.solids:
            builder.Add(comp, s)
        return comp

    @cached_property
    def volume_mm3(self) -> float:
        """Exact volume of all solids (see ``solid_volume``); computed on first use."""
        return float(sum(solid_volume(s) for s in self.solids))


def occt_version() -> str:
    """The OCCT release in use: cadquery-ocp's version is OCCT's and a build number (8.0.1.0)."""
    import OCP

    return ".".join(str(OCP.__version__).split(".")[:3])


def read_step(path: str | os.PathLike[str]) -> LoadedPart:
    """Read ``path`` and return its closed solids.

    Raises
    ------
    StepReadError
        Not a Part 21 file, or OCCT could not read it or transfer anything.
    EmptyGeometryError
        Read, but no faces at all.
    NotASolidError
        Faces, but no closed solid even after sewing.
    """
    path = os.fspath(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(SNIFF_BYTES)
    except OSError as exc:
        raise StepReadError(f"cannot open {os.path.basename(path)}: {exc.strerror}") from None
    if not head:
        raise StepReadError("the file is empty")
    if not sniff_step(head):
        raise StepReadError("not a STEP file: it does not start with the ISO-10303-21 header")

    reader = STEPControl_Reader()
    status = reader.ReadFile(path)
    if status != IFSelect_ReturnStatus.IFSelect_RetDone:
        raise StepReadError(f"OCCT could not parse the STEP file (status {status.name})")
    units = _file_units(reader)
    if reader.NbRootsForTransfer() == 0:
        raise EmptyGeometryError("the STEP file holds no shape to transfer")
    reader.TransferRoots()
    if reader.NbShapes() == 0:
        raise StepReadError("no shape in the STEP file could be transferred (broken entities?)")
    shape = reader.OneShape()
    if shape.IsNull() or _count(shape, TopAbs_FACE) == 0:
        raise EmptyGeometryError("the STEP file holds no faces (only wireframe, points or metadata?)")

    warnings: list[str] = []
    non_mm = [u for u in units if u.upper() not in {"MM", "MILLIMETRE", "MILLIMETER"}]
    if non_mm:
        warnings.append(f"units converted to mm from the file's {', '.join(sorted(set(non_mm)))}")

    solids = _solids(shape)
    sewn = False
    loose_faces = _faces_outside_solids(shape)
    if not solids:
        solids = _sew_into_solids(shape)
        if not solids:
            raise NotASolidError(
                "the STEP file holds surfaces but no closed solid, and sewing does not close them"
            )
        sewn = True
        warnings.append(f"open shells were sewn into {len(solids)} closed solid(s)")
    elif loose_faces:
        warnings.append(f"{loose_faces} face(s) outside any solid were ignored (surfaces, open shells)")

    split, widest = 0, 0.0
    for k, solid in enumerate(solids):
        healed = split_loose_vertices(solid)
        if healed is not None:
            solids[k], n, gap = healed
            split, widest = split + n, max(widest, gap)
    if split:
        warnings.append(
            f"{split} vertex(es) of the file joined corners up to {widest:.3g} mm apart (a coarse tolerance "
            "in the file); each was split into its separate corners"
        )
    return LoadedPart(solids=solids, source_units=units, warnings=warnings, sewn=sewn)


def rotation_matrix(rotation: tuple[float, float, float]) -> np.ndarray:
    """The 3 x 3 matrix turning a part ``rotation[0]`` degrees about x, then ``rotation[1]`` about y,
    then ``rotation[2]`` about z (fixed axes, right-handed: 90 about x takes +y to +z). Multiples of
    90 degrees give exact 0 and +-1 entries, so a face that the turn makes horizontal is exactly
    horizontal (cos(pi / 2) is 6e-17 in floating point, which would tilt it)."""
    m = np.eye(3)
    for axis, deg in enumerate(rotation):
        c, s = _cos_sin(deg)
        i, j = [(1, 2), (2, 0), (0, 1)][axis]  # the plane the turn about ``axis`` acts in
        r = np.eye(3)
        r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
        m = r @ m
    return m


def _cos_sin(deg: float) -> tuple[float, float]:
    quarter, rest = divmod(float(deg), 90.0)
    if rest == 0.0:
        return [(1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0)][int(quarter) % 4]
    rad = np.radians(deg)
    return float(np.cos(rad)), float(np.sin(rad))


def orient(part: LoadedPart, rotation: tuple[float, float, float]) -> LoadedPart:
    """``part`` turned by ``rotation`` (see ``rotation_matrix``) about the origin, as the part is to be
    printed: the slicing planes are horizontal in the turned part. The solids' curves and surfaces
    are transformed (copies; the part itself is not changed), so no placement is left on them.
    Returns ``part`` itself when it already has this rotation; a part read with another one is
    turned from the file's placement again, never on top of it."""
    rotation = (float(rotation[0]), float(rotation[1]), float(rotation[2]))
    if rotation == part.rotation:
        return part
    if part.rotation != NO_ROTATION:
        raise ValueError(f"the part is already turned by {part.rotation}; orient the file's part instead")
    m = rotation_matrix(rotation)
    trsf = gp_Trsf()
    trsf.SetValues(*m[0], 0.0, *m[1], 0.0, *m[2], 0.0)
    solids = []
    for solid in part.solids:
        turned = BRepBuilderAPI_Transform(solid, trsf, True).Shape()
        solids.append(TopoDS.Solid(turned))
    return LoadedPart(
        solids=solids,
        source_units=part.source_units,
        warnings=list(part.warnings),
        sewn=part.sewn,
        rotation=rotation,
    )


VOLUME_REL_EPS = 1e-8


def solid_volume(solid: TopoDS_Shape) -> float:
    """Volume in mm^3 by OCCT's adaptive Gauss integration on the B-rep, to a relative error of 1e-8.

    (The non-adaptive ``VolumeProperties`` is off by about 1% on a NURBS hemisphere.)
    """
    props = GProp_GProps()
    BRepGProp.VolumeProperties_s(solid, props, VOLUME_REL_EPS, True)
    return props.Mass()


def split_loose_vertices(solid: TopoDS_Solid) -> tuple[TopoDS_Solid, int, float] | None:
    """Give back their own vertices to corners that one over-tolerant vertex joins.

    A file written with a coarse tolerance (say 1 mm) can make distinct corners of a narrow face one
    vertex, whose tolerance then covers them all: a 1 mm wide strip whose four corners are two
    vertices. Every mesher then puts one node for all those corners, and the mesh folds there.
    Here, the edge ends at each vertex whose tolerance exceeds ``LOOSE_VERTEX_GAP_MM`` are grouped
    by position (single linkage at that gap); a vertex whose ends form several groups is replaced
    by one vertex per group (at the group's centre, its tolerance the group's radius), on copies of
    its edges that keep their curves and pcurves. The result is kept only when OCCT finds it a
    valid solid (a split that disconnects a wire is not); otherwise None, as when nothing is split.

    Returns (solid, vertices split, widest distance between the corners they joined, mm) or None.
    """
    vertex_edges = ShapeAncestorMap()
    TopExp.MapShapesAndAncestors_s(solid, TopAbs_VERTEX, TopAbs_EDGE, vertex_edges)
    builder = BRep_Builder()
    new_ends: list[tuple[TopoDS_Edge, dict[int, TopoDS_Vertex]]] = []  # (edge, end 0/1 -> vertex)

    def ends_of(edge: TopoDS_Edge) -> dict[int, TopoDS_Vertex]:
        for known, vertex_of in new_ends:
            if known.IsSame(edge):
                return vertex_of
        new_ends.append((edge, {}))
        return new_ends[-1][1]

    n_split, widest = 0, 0.0
    for i in range(1, vertex_edges.Extent() + 1):
        vertex = TopoDS.Vertex(vertex_edges.FindKey(i))
        if BRep_Tool.Tolerance_s(vertex) <= LOOSE_VERTEX_GAP_MM:
            continue
        ends: list[tuple[TopoDS_Edge, int]] = []
        points: list[tuple[float, float, float]] = []
        for shape in vertex_edges.FindFromIndex(i):
            edge = TopoDS.Edge(shape.Oriented(TopAbs_FORWARD))
            if any(e.IsSame(edge) for e, _ in ends):
                continue  # a seam appears twice
            if BRep_Tool.Degenerated_s(edge):
                break  # a pole: its vertex has no corners to tell apart
            curve = BRepAdaptor_Curve(edge)
            for end, (v, t) in enumerate(
                (
                    (TopExp.FirstVertex_s(edge), curve.FirstParameter()),
                    (TopExp.LastVertex_s(edge), curve.LastParameter()),
                )
            ):
                if v.IsSame(vertex):
                    ends.append((edge, end))
                    points.append(curve.Value(t).Coord())
        else:
            if len(points) < 2:
                continue
            pts = np.array(points)
            labels = fcluster(linkage(pts, "single"), LOOSE_VERTEX_GAP_MM, criterion="distance")
            if labels.max() == 1:
                continue
            n_split += 1
            widest = max(widest, float(pdist(pts).max()))
            for label in np.unique(labels):
                group = pts[labels == label]
                centre = group.mean(axis=0)
                tol = max(float(np.linalg.norm(group - centre, axis=1).max()) * 1.001, VERTEX_MIN_TOL_MM)
                new_vertex = TopoDS_Vertex()
                builder.MakeVertex(new_vertex, gp_Pnt(*centre), tol)
                for (edge, end), lab in zip(ends, labels, strict=True):
                    if lab == label:
                        ends_of(edge)[end] = new_vertex
    if not n_split:
        return None

    reshape = BRepTools_ReShape()
    for edge, vertex_of in new_ends:
        copy = TopoDS.Edge(edge.EmptyCopied())  # same curves, pcurves, range and tolerance; no vertices
        first, last = BRep_Tool.Range_s(edge)
        for end, old, param, orientation in (
            (0, TopExp.FirstVertex_s(edge), first, TopAbs_FORWARD),
            (1, TopExp.LastVertex_s(edge), last, TopAbs_REVERSED),
        ):
            vertex = vertex_of.get(end, old)
            builder.Add(copy, vertex.Oriented(orientation))
            if end in vertex_of:
                builder.UpdateVertex(vertex, param, copy, BRep_Tool.Tolerance_s(vertex))
        reshape.Replace(edge, copy)
    healed = reshape.Apply(solid)
    if not _valid_closed_solid(healed):
        return None
    return TopoDS.Solid(healed), n_split, widest


def heal_wires(solid: TopoDS_Solid, precision: float) -> tuple[TopoDS_Solid, float] | None:
    """Close the gaps in the solid's face boundaries and drop its edges shorter than ``precision``
    (OCCT's ``ShapeFix_Wireframe``): a face whose wire has zero-length edges and gaps cannot be
    meshed. Kept only if OCCT finds the result a valid closed solid whose volume differs by less
    than ``HEAL_VOLUME_REL``; otherwise, or when nothing was fixed, None.

    Returns (solid, relative volume change).
    """
    fix = ShapeFix_Wireframe(solid)
    fix.SetPrecision(precision)
    fix.ModeDropSmallEdges = True
    gaps, small = fix.FixWireGaps(), fix.FixSmallEdges()
    if not (gaps or small):
        return None
    healed = fix.Shape()
    if not _valid_closed_solid(healed):
        return None
    before = solid_volume(solid)
    change = abs(solid_volume(healed) - before) / abs(before)
    if change > HEAL_VOLUME_REL:
        return None
    return TopoDS.Solid(healed), change


def _valid_closed_solid(shape: TopoDS_Shape) -> bool:
    """A repair is kept only if its result is one solid that OCCT finds valid and that is closed."""
    return shape.ShapeType() == TopAbs_SOLID and BRepCheck_Analyzer(shape).IsValid() and _is_closed(shape)


def _file_units(reader: STEPControl_Reader) -> list[str]:
    lengths, angles, solid_angles = (Sequence_TCollection_AsciiString() for _ in range(3))
    reader.FileUnits(lengths, angles, solid_angles)
    return [lengths.Value(i).ToCString() for i in range(1, lengths.Length() + 1)]


def _count(shape: TopoDS_Shape, kind) -> int:
    exp, n = TopExp_Explorer(shape, kind), 0
    while exp.More():
        n += 1
        exp.Next()
    return n


def _solids(shape: TopoDS_Shape) -> list[TopoDS_Solid]:
    out = []
    exp = TopExp_Explorer(shape, TopAbs_SOLID)
    while exp.More():
        solid = TopoDS.Solid(exp.Current())
        if _is_closed(solid):
            out.append(solid)
        exp.Next()
    return out


def _faces_outside_solids(shape: TopoDS_Shape) -> int:
    exp = TopExp_Explorer(shape, TopAbs_FACE, TopAbs_SOLID)
    n = 0
    while exp.More():
        n += 1
        exp.Next()
    return n


def _is_closed(shape: TopoDS_Shape) -> bool:
    """Every edge is shared by two faces (degenerate edges and seams excepted)."""
    if _count(shape, TopAbs_FACE) == 0:
        return False
    edge_faces = ShapeAncestorMap()
    TopExp.MapShapesAndAncestors_s(shape, TopAbs_EDGE, TopAbs_FACE, edge_faces)
    for i in range(1, edge_faces.Extent() + 1):
        edge = TopoDS.Edge(edge_faces.FindKey(i))
        if BRep_Tool.Degenerated_s(edge):
            continue
        faces = edge_faces.FindFromIndex(i)
        if faces.Size() < 2:
            return False
    return True


def _sew_into_solids(shape: TopoDS_Shape) -> list[TopoDS_Solid]:
    sewing = BRepBuilderAPI_Sewing(SEWING_TOL_MM)
    sewing.Add(shape)
    sewing.Perform()
    sewn = sewing.SewedShape()
    out: list[TopoDS_Solid] = []
    exp = TopExp_Explorer(sewn, TopAbs_SHELL)
    while exp.More():
        shell = TopoDS.Shell(exp.Current())
        if _is_closed(shell):
            maker = BRepBuilderAPI_MakeSolid(shell)
            if maker.IsDone():
                fixer = ShapeFix_Solid(maker.Solid())
                fixer.Perform()
                solid = TopoDS.Solid(fixer.Solid())
                if BRepCheck_Analyzer(solid).IsValid():
                    out.append(solid)
        exp.Next()
    return out
