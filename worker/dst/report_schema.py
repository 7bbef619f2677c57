"""The deviation report's JSON contract (versioned): pydantic models, free of the geometry kernel, so
that the API can publish the report's schema (``Report.model_json_schema()``) without loading OCCT.
``report.build_report`` fills them."""

from __future__ import annotations

from typing import Final, Literal

from pydantic import BaseModel, ConfigDict, Field

from worker.dst.params import SliceParams

REPORT_VERSION: Final = "1.1"  # 1.1: layers carry flat_side (flat faces on planes measured on both sides)


class Summary(BaseModel):
    """Statistics of the per-layer metrics over the layers where they are defined."""

    max_vertex_dev: float | None = Field(None, ge=0, description="Largest layer vertex_dev, mm.")
    mean_vertex_dev: float | None = Field(None, ge=0, description="Mean of the layers' vertex_dev, mm.")
    p95_vertex_dev: float | None = Field(None, ge=0, description="95th percentile of vertex_dev, mm.")
    max_chord_dev: float | None = Field(None, ge=0, description="Largest layer chord_dev, mm.")
    mean_chord_dev: float | None = Field(None, ge=0, description="Mean of the layers' chord_dev, mm.")
    p95_chord_dev: float | None = Field(None, ge=0, description="95th percentile of chord_dev, mm.")
    max_perimeter_err: float | None = Field(None, ge=0, description="Largest relative perimeter error.")
    mean_perimeter_err: float | None = Field(None, ge=0, description="Mean relative perimeter error.")
    p95_perimeter_err: float | None = Field(None, ge=0, description="95th percentile of perimeter_err.")
    layers_missing: int = Field(
        0, ge=0, description="Layers where the exact section exists but the mesh cut is empty."
    )
    layers_extra: int = Field(
        0, ge=0, description="Layers where the mesh cut exists but the exact section is empty."
    )
    layers_loop_mismatch: int = Field(
        0, ge=0, description="Layers whose loop count differs from the exact one."
    )


class Layer(BaseModel):
    """One slicing plane: the mesh's cut there against the exact section."""

    index: int = Field(ge=0, description="Plane index, 0 = first layer.")
    z: float = Field(description="Plane height above the lowest point, mm (as the slicer computes it).")
    vertex_dev: float | None = Field(
        None, ge=0, description="Max distance of the cut's vertices from the exact section, mm (eq. 1)."
    )
    chord_dev: float | None = Field(
        None, ge=0, description="Two-sided max distance between the cut polyline and the exact section, mm."
    )
    perimeter_err: float | None = Field(
        None, ge=0, description="|L_exact - L_cut| / L_exact (eq. 2); 1 when the cut is empty."
    )
    loops: int = Field(ge=0, description="Closed loops of the cut.")
    loops_exact: int = Field(ge=0, description="Loops of the exact section.")
    open_chains: int = Field(0, ge=0, description="Cut chains that do not close (holes in the mesh).")
    vertices: int = Field(ge=0, description="Vertices of the cut.")
    flat_side: Literal["above", "below"] | None = Field(
        None,
        description=(
            "At a plane through a flat face (whose exact section is an area): which exact outline the "
            "cut was measured against, the one just above the face or just below it, whichever the cut "
            "matches better (slicers differ: Cura keeps the outline above, PrusaSlicer the one below). "
            "None at other planes."
        ),
    )


class MeshReport(BaseModel):
    name: str = Field(description="'dst', a baseline preset name, or the measured file's name.")
    kind: Literal["dst", "baseline", "input"] = Field(
        description="What the mesh is: this job's DST mesh, a conventional baseline, or a mesh given to measure."
    )
    description: str = Field("", description="How the mesh was made.")
    triangles: int = Field(ge=0, description="Triangles of the mesh (degenerate ones dropped).")
    vertices: int = Field(ge=0, description="Distinct vertices (equal float32 coordinates merged).")
    stl_bytes: int = Field(ge=0, description="Size as binary STL, bytes.")
    watertight: bool = Field(description="Closed, consistently oriented 2-manifold.")
    open_edges: int = Field(ge=0, description="Edges with one triangle (holes).")
    nonmanifold_edges: int = Field(ge=0, description="Edges with more than two triangles.")
    volume_mm3: float = Field(description="Enclosed (signed) volume, mm^3.")
    volume_rel_err: float | None = Field(None, description="(mesh volume - exact volume) / exact volume.")
    seconds: float | None = Field(
        None,
        ge=0,
        description="Time taken to build the mesh, s (None if not built here); a baseline made on one "
        "thread: its CPU seconds, the time it takes on a core of its own (the description says so).",
    )
    summary: Summary = Field(description="Statistics of the per-layer metrics.")
    ratios: dict[str, float | None] | None = Field(
        None, description="This mesh's summary metric / DST's (baselines only); None where DST's is 0."
    )
    layers: list[Layer] = Field(description="One entry per slicing plane, in order.")


class InputInfo(BaseModel):
    file: str = Field(description="The STEP file's name.")
    source_units: list[str] = Field(description="Length units declared in the file (converted to mm).")
    solids: int = Field(ge=0, description="Solids in the file (each measured).")
    bbox_min: tuple[float, float, float] = Field(
        description="Exact-lowest-point-based box corner, mm (file coordinates)."
    )
    bbox_max: tuple[float, float, float] = Field(
        description="The box's opposite corner, mm (file coordinates)."
    )
    height_mm: float = Field(ge=0, description="Exact height (highest minus lowest point), mm.")
    volume_mm3: float = Field(description="Exact B-rep volume, mm^3.")


class ReferenceInfo(BaseModel):
    method: str = Field(description="How the exact section points were computed.")
    chord_mm: float = Field(
        description="Largest distance between the exact curves and the reference polylines, mm."
    )
    spacing_mm: float = Field(
        description="Spacing of the points along the reference's spans (and a cut's segments) that index "
        "the nearest-span search, mm: every distance is then to the span or segment itself."
    )
    resolution_mm: float = Field(
        description="Reported distances are within this of the distances to the exact section curves, mm."
    )
    distances: str = Field(description="How the distances were computed.")
    seconds: float = Field(ge=0, description="Time taken to compute the reference, s.")
    loops: int = Field(ge=0, description="Exact section loops over all planes.")


class Report(BaseModel):
    """A deviation report (JSON contract, versioned)."""

    model_config = ConfigDict(extra="forbid")

    version: Literal["1.1"] = Field(REPORT_VERSION, description="Version of this contract.")
    input: InputInfo = Field(description="The STEP file and its exact geometry.")
    params: SliceParams = Field(description="The slicing parameters the planes and the DST mesh follow.")
    planes: list[float] = Field(description="Plane heights above the lowest point, mm, one per layer.")
    reference: ReferenceInfo = Field(description="How the exact sections were computed.")
    meshes: list[MeshReport] = Field(
        description="DST (or the mesh given to measure) first, then the baselines in the order asked for."
    )
    warnings: list[str] = Field(description="What a user must see before trusting or printing the mesh.")
