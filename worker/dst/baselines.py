"""The conventional meshes a deviation report compares DST with: named BRepMesh presets.

Plain data (no OCCT), so the API can validate a job's baselines without loading the geometry kernel.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from worker.dst.errors import InvalidParameters


@dataclass(frozen=True)
class Preset:
    linear: float  # BRepMesh linear deflection, mm
    angular: float  # BRepMesh angular deflection, rad
    source: str
    # A slicer's STEP import: the slicer, and the OCCT release it links (its deps build pins it). The
    # report meshes with the same parameters on its own OCCT, whose BRepMesh can make another mesh.
    app: str | None = None
    app_occt: str | None = None


BASELINE_PRESETS: dict[str, Preset] = {
    "occt_fast": Preset(0.085, 0.5, "paper Table 1 'fast' (angular: OCCT's default 0.5 rad)"),
    "occt_high_quality": Preset(0.037, 0.5, "paper Table 1 'high quality' (angular: OCCT's default 0.5 rad)"),
    "occt_reference": Preset(0.00576, 0.5, "paper Table 1 'reference' (angular: OCCT's default 0.5 rad)"),
    # PrusaSlicer pins OCCT 7.6.1 (deps/+OCCT/OCCT.cmake: later releases triangulate chamfers wrongly);
    # Bambu Studio and OrcaSlicer build 7.6.0 (deps/OCCT/OCCT.cmake)
    "prusaslicer": Preset(
        0.005, 1.0, "PrusaSlicer 2.5 STEP import (OCCTWrapper.cpp)", "PrusaSlicer", "7.6.1"
    ),
    "bambu_orca": Preset(
        0.003,
        0.5,
        "Bambu Studio / OrcaSlicer STEP import (Format/STEP.cpp)",
        "Bambu Studio / OrcaSlicer",
        "7.6.0",
    ),
    "prusaslicer_high": Preset(
        0.001, 0.25, "PrusaSlicer 'High' STEP import (LoadStepDialog.cpp)", "PrusaSlicer", "7.6.1"
    ),
}
DEFAULT_BASELINES = ("occt_fast", "occt_high_quality", "prusaslicer")
# What ``parse_baselines`` accepts as a string, for the API's schema: comma-separated items, each a
# preset's name, 'none' or empty, spaces round them allowed
_ITEM = r"\s*(" + "|".join(["none", *BASELINE_PRESETS]) + r")?\s*"
BASELINES_PATTERN = rf"^{_ITEM}(,{_ITEM})*$"


def parse_baselines(names: Sequence[str] | str | None) -> tuple[str, ...]:
    """Baseline preset names from a list or a comma-separated string ('none' or '' for none)."""
    if names is None:
        return DEFAULT_BASELINES
    if isinstance(names, str):
        names = [n.strip() for n in names.split(",")]
    names = [n for n in names if n and n != "none"]
    unknown = [n for n in names if n not in BASELINE_PRESETS]
    if unknown:
        raise InvalidParameters(
            f"unknown baseline {', '.join(unknown)}; choose from {', '.join(BASELINE_PRESETS)} or 'none'"
        )
    return tuple(dict.fromkeys(names))
