"""Warnings a user must see about how the slicer will treat the part."""

from __future__ import annotations

from OCP.BRepAdaptor import BRepAdaptor_Surface
from OCP.GeomAbs import GeomAbs_Plane
from OCP.TopAbs import TopAbs_FACE
from OCP.TopExp import TopExp_Explorer
from OCP.TopoDS import TopoDS, TopoDS_Shape

from worker.dst.constants import ON_PLANE_TOL_MM
from worker.dst.planes import PlanePlan

_HORIZONTAL_COS = 1.0 - 1e-12  # |normal . z| above this: the plane face is horizontal


def flat_faces_on_planes(solids: list[TopoDS_Shape], *, zmin: float, planes: PlanePlan) -> list[str]:
    """One warning per slicing plane that contains a horizontal planar face of the part.

    Such a layer is ambiguous for every slicer: the exact section there is an area, not a curve.
    """
    hits: dict[int, float] = {}
    for solid in solids:
        exp = TopExp_Explorer(solid, TopAbs_FACE)
        while exp.More():
            face = TopoDS.Face(exp.Current())
            exp.Next()
            ad = BRepAdaptor_Surface(face)
            if ad.GetType() != GeomAbs_Plane:
                continue
            pln = ad.Plane()
            if abs(pln.Axis().Direction().Z()) < _HORIZONTAL_COS:
                continue
            rel = pln.Location().Z() - zmin
            j = int(abs(planes.z - rel).argmin()) if len(planes) else -1
            if j >= 0 and abs(float(planes.z[j]) - rel) <= ON_PLANE_TOL_MM:
                hits[j] = rel
    return [
        f"a flat face lies on slicing plane {j} (z = {planes.z[j]:.4f} mm): the section there is an area, "
        "and slicers disagree on it (Cura keeps the outline above the face, PrusaSlicer the one below); "
        "the DST mesh keeps one ring there"
        for j in sorted(hits)
    ]
