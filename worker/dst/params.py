"""Slicing parameters: one validated model shared by the CLI, the worker and the API."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from worker.dst.constants import CHORD_ERROR_RANGE_MM, LAYER_HEIGHT_RANGE_MM, SEGMENT_LENGTH_RANGE_MM
from worker.dst.errors import InvalidParameters

ROTATION_FIELDS = ("rotate_x", "rotate_y", "rotate_z")
SlicingMode = Literal["middle", "inclusive", "exclusive"]
TargetSlicer = Literal["cura", "prusa"]


class SliceParams(BaseModel):
    """What a DST job needs to know about the slicer that will cut its mesh, and the part's print
    orientation. Lengths in mm, angles in degrees."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    layer_height: float = Field(
        0.2, ge=LAYER_HEIGHT_RANGE_MM[0], le=LAYER_HEIGHT_RANGE_MM[1], description="Layer height h, mm."
    )
    first_layer_height: float | None = Field(
        None,
        ge=LAYER_HEIGHT_RANGE_MM[0],
        le=LAYER_HEIGHT_RANGE_MM[1],
        description="First-layer height h0, mm; defaults to the layer height.",
    )
    mode: SlicingMode = Field(
        "middle",
        description="Slicing tolerance: 'middle' slices mid-layer (Cura default, PrusaSlicer, Orca, Bambu); "
        "'inclusive'/'exclusive' slice the layer boundaries (Cura).",
    )
    segment_length: float = Field(
        0.8,
        ge=SEGMENT_LENGTH_RANGE_MM[0],
        le=SEGMENT_LENGTH_RANGE_MM[1],
        description="Longest segment allowed along a section curve, mm.",
    )
    chord_error: float = Field(
        0.025,
        ge=CHORD_ERROR_RANGE_MM[0],
        le=CHORD_ERROR_RANGE_MM[1],
        description="Largest distance allowed between a section curve and its polyline, mm.",
    )
    target_slicer: TargetSlicer | None = Field(
        None,
        description="Write ring heights exactly as this slicer computes its planes "
        "(Cura: integer micrometres; PrusaSlicer: float32 of its accumulated double).",
    )

    rotate_x: float = Field(
        0.0,
        ge=-360.0,
        le=360.0,
        description="Turn the part this many degrees about the x axis before slicing (first), as it is "
        "to be printed: the DST mesh is only exact in the orientation it was made for.",
    )
    rotate_y: float = Field(
        0.0, ge=-360.0, le=360.0, description="Then this many degrees about the y axis (second)."
    )
    rotate_z: float = Field(
        0.0, ge=-360.0, le=360.0, description="Then this many degrees about the z axis (last)."
    )

    @model_validator(mode="after")
    def _chord_below_segment(self) -> SliceParams:
        if self.chord_error >= self.segment_length:
            raise ValueError(
                f"chord_error ({self.chord_error} mm) must be smaller than segment_length "
                f"({self.segment_length} mm)"
            )
        return self

    @model_validator(mode="after")
    def _prusa_slices_mid_layer(self) -> SliceParams:
        # refused here, with the request, not when the job plans its planes
        if self.target_slicer == "prusa" and self.mode != "middle":
            raise ValueError(
                f"target_slicer 'prusa' only slices in 'middle' mode (PrusaSlicer has no slicing-tolerance "
                f"setting), got mode '{self.mode}'"
            )
        return self

    @property
    def h0(self) -> float:
        """The first-layer height actually used, mm."""
        return self.layer_height if self.first_layer_height is None else self.first_layer_height

    @property
    def rotation(self) -> tuple[float, float, float]:
        """Degrees about the fixed x, y and z axes, applied in that order (right-handed)."""
        return (self.rotate_x, self.rotate_y, self.rotate_z)

    @classmethod
    def parse(cls, **values: object) -> SliceParams:
        """Validate user input, raising :class:`InvalidParameters` with one readable line per problem."""
        try:
            return cls(**{k: v for k, v in values.items() if v is not None})
        except ValidationError as exc:
            raise InvalidParameters(describe_validation_error(exc)) from None


# The slicing fields by name, in the model's order: what every front end (the CLI's options, the API's
# form fields and job schema) passes through to ``SliceParams.parse``.
SLICING_FIELDS: tuple[str, ...] = tuple(SliceParams.model_fields)


def describe_validation_error(exc: ValidationError) -> str:
    """One line a user can act on: 'layer_height must be between 0.01 and 2 mm, got 50'."""
    parts = []
    for err in exc.errors():
        name = ".".join(str(p) for p in err["loc"]) or "parameters"
        field = SliceParams.model_fields.get(name)
        got = err.get("input")
        if field is not None and err["type"] in {"greater_than_equal", "less_than_equal"}:
            lo = next((m.ge for m in field.metadata if hasattr(m, "ge")), None)
            hi = next((m.le for m in field.metadata if hasattr(m, "le")), None)
            unit = "degrees" if name in ROTATION_FIELDS else "mm"
            parts.append(f"{name} must be between {lo:g} and {hi:g} {unit}, got {got}")
        elif err["type"] == "value_error":
            parts.append(str(err["msg"]).removeprefix("Value error, "))
        else:
            parts.append(f"{name}: {err['msg']} (got {got!r})")
    return "; ".join(parts)
