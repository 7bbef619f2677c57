"""Read a STEP file into closed solids in millimetres, with the warnings a user must see.

OCCT's ``STEPControl_Reader`` is used directly (not build123d's ``import_step``, which returns an
empty shape for empty, truncated and non-STEP files). Placements of assembly instances are applied
by ``OneShape``; lengths are converted to millimetres by the reader whatever the file's unit.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from functools import cached_property

from OCP.BRep import BRep_Builder
from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeSolid, BRepBuilderAPI_Sewing
from OCP.BRepCheck import BRepCheck_Analyzer
from OCP.BRepGProp import BRepGProp
from OCP.collections import (
    IndexedDataMap_TopoDS_Shape_List_TopoDS_Shape_TopTools_ShapeMapHasher as ShapeAncestorMap,
)
from OCP.collections import Sequence_TCollection_AsciiString
from OCP.GProp import GProp_GProps
from OCP.IFSelect import IFSelect_ReturnStatus
from OCP.ShapeFix import ShapeFix_Solid
from OCP.STEPControl import STEPControl_Reader
from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE, TopAbs_SHELL, TopAbs_SOLID
from OCP.TopExp import TopExp, TopExp_Explorer
from OCP.TopoDS import TopoDS, TopoDS_Compound, TopoDS_Shape, TopoDS_Solid

from worker.dst.errors import EmptyGeometryError, NotASolidError, StepReadError
from worker.dst.sniff import SNIFF_BYTES, sniff_step

SEWING_TOL_MM = 1e-3  # gaps up to 1 um between open shells' edges are closed by sewing


@dataclass
class LoadedPart:
    """Closed solids read from one STEP file, all in millimetres and in the file's placement."""

    solids: list[TopoDS_Solid]
    source_units: list[str]
    warnings: list[str] = field(default_factory=list)
    sewn: bool = False

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
    return LoadedPart(solids=solids, source_units=units, warnings=warnings, sewn=sewn)


VOLUME_REL_EPS = 1e-8


def solid_volume(solid: TopoDS_Shape) -> float:
    """Volume in mm^3 by OCCT's adaptive Gauss integration on the B-rep, to a relative error of 1e-8.

    (The non-adaptive ``VolumeProperties`` is off by about 1% on a NURBS hemisphere.)
    """
    props = GProp_GProps()
    BRepGProp.VolumeProperties_s(solid, props, VOLUME_REL_EPS, True)
    return props.Mass()


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
    from OCP.BRep import BRep_Tool

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
