"""Real slicers (CuraEngine and PrusaSlicer, from Debian) cut the DST mesh exactly along its rings.

The outer wall of a correct mesh sits at a constant inset (about half the line width) from the exact
section on every layer; its spread around that inset is the as-printed deviation (DST.md section 5).
A conventional mesh of the same part must show a clearly larger spread, or the test proves nothing.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import build_part, write_step
from worker.dst.params import SliceParams
from worker.dst.pipeline import slice_step

pytestmark = pytest.mark.slicer

_DEF_DIRS = [
    os.environ.get("DST_CURA_DEFINITIONS", ""),
    str(Path.home() / ".cache" / "dst" / "cura-definitions"),
    "/usr/share/cura/resources/definitions",
]


def _cura() -> tuple[str, Path]:
    exe = shutil.which("CuraEngine")
    defs = next((Path(d) for d in _DEF_DIRS if d and (Path(d) / "fdmprinter.def.json").is_file()), None)
    if exe is None or defs is None:
        pytest.skip("CuraEngine or its fdmprinter definitions are not installed (.ci/run installs both)")
    return exe, defs


def _outer_wall_radii(gcode: str) -> dict[int, np.ndarray]:
    """Distances from the z axis of the outer-wall extrusion end points, per layer."""
    layers: dict[int, list[float]] = {}
    layer, kind = -1, ""
    move = re.compile(r"^G1 .*X(-?[\d.]+) Y(-?[\d.]+) E")
    for line in gcode.splitlines():
        if line.startswith(";LAYER:"):
            layer = int(line[7:])
        elif line.startswith(";TYPE:"):
            kind = line[6:]
        elif kind == "WALL-OUTER" and (m := move.match(line)):
            layers.setdefault(layer, []).append(float(np.hypot(float(m.group(1)), float(m.group(2)))))
    return {k: np.array(v) for k, v in layers.items()}


def _cura_spread(stl: Path, tmp: Path, *, radius: float, h: float) -> float:
    exe, defs = _cura()
    gcode = tmp / (stl.stem + ".gcode")
    settings = {
        "layer_height": h,
        "layer_height_0": h,
        "machine_center_is_zero": "true",
        "meshfix_maximum_resolution": 0.05,
        "meshfix_maximum_deviation": 0.002,
        "wall_line_count": 1,
        "infill_sparse_density": 0,
        "top_layers": 0,
        "bottom_layers": 0,
        "adhesion_type": "none",
    }
    cmd = [exe, "slice", "-j", str(defs / "fdmprinter.def.json")]
    for k, v in settings.items():
        cmd += ["-s", f"{k}={v}"]
    cmd += ["-l", str(stl), "-o", str(gcode)]
    subprocess.run(cmd, check=True, capture_output=True, timeout=300)
    walls = _outer_wall_radii(gcode.read_text())
    insets = []
    for layer, r in walls.items():
        z = h / 2 + layer * h
        exact = np.sqrt(radius**2 - z**2)
        if exact < 3.0:  # near the pole Cura shortens tiny loops on its own: not the mesh's doing
            continue
        insets.append(exact - r)
    insets = np.concatenate(insets)
    return float(insets.max() - insets.min())


def _prusa_spread(stl: Path, tmp: Path, *, radius: float, h: float) -> float:
    exe = shutil.which("prusa-slicer")
    if exe is None:
        pytest.skip("prusa-slicer is not installed (.ci/run installs it)")
    gcode = tmp / (stl.stem + "_prusa.gcode")
    cmd = [
        exe,
        "--export-gcode",
        "--layer-height",
        str(h),
        "--first-layer-height",
        str(h),
        "--center",
        "0,0",
        "--dont-arrange",
        "--perimeters",
        "1",
        "--fill-density",
        "0",
        "--top-solid-layers",
        "0",
        "--bottom-solid-layers",
        "0",
        "--skirts",
        "0",
        "--gcode-resolution",
        "0.002",
        "--output",
        str(gcode),
        str(stl),
    ]
    subprocess.run(cmd, check=True, capture_output=True, timeout=300, env={**os.environ, "HOME": str(tmp)})
    insets, print_z, kind = [], None, ""
    move = re.compile(r"^G1 X(-?[\d.]+) Y(-?[\d.]+) E")
    for line in gcode.read_text().splitlines():
        if line.startswith(";Z:"):
            print_z = float(line[3:])
        elif line.startswith(";TYPE:"):
            kind = line[6:]
        # the first layer is printed with a wider extrusion, hence another inset: it is left out
        elif (
            kind == "External perimeter"
            and print_z is not None
            and print_z > 1.5 * h
            and (m := move.match(line))
        ):
            z = print_z - h / 2  # PrusaSlicer slices mid-layer
            exact = np.sqrt(radius**2 - z**2)
            if exact >= 3.0:
                insets.append(exact - float(np.hypot(float(m.group(1)), float(m.group(2)))))
    insets = np.array(insets)
    return float(insets.max() - insets.min())


@pytest.fixture(scope="module")
def hemisphere_meshes(tmp_path_factory):
    """The DST hemisphere and OCCT's conventional mesh at the paper's "fast" preset (0.085 mm)."""
    tmp_path = tmp_path_factory.mktemp("slicers")
    step = write_step(build_part("hemisphere", radius=20.0), tmp_path / "hemi.step")
    dst = tmp_path / "hemi_dst.stl"
    slice_step(step, SliceParams(layer_height=0.2)).write_stl(dst)
    import trimesh
    from OCP.BRepMesh import BRepMesh_IncrementalMesh
    from OCP.StlAPI import StlAPI_Writer

    from worker.dst.step_io import read_step

    solid = read_step(step).solids[0]
    BRepMesh_IncrementalMesh(solid, 0.085, False, 0.5, True)
    conv = tmp_path / "hemi_conv.stl"
    writer = StlAPI_Writer()
    writer.ASCIIMode = False
    writer.Write(solid, str(conv))
    assert trimesh.load(conv).bounds[0][2] == pytest.approx(0.0, abs=1e-6)
    return tmp_path, dst, conv


@pytest.mark.parametrize(
    ("spread", "dst_max", "factor"),
    [(_cura_spread, 0.02, 5.0), (_prusa_spread, 0.03, 3.0)],
    ids=["curaengine", "prusaslicer"],
)
def test_outer_wall_keeps_a_constant_inset_on_the_dst_hemisphere(hemisphere_meshes, spread, dst_max, factor):
    tmp_path, dst, conv = hemisphere_meshes
    dst_spread = spread(dst, tmp_path, radius=20.0, h=0.2)
    conv_spread = spread(conv, tmp_path, radius=20.0, h=0.2)
    assert dst_spread < dst_max, f"DST outer wall spread {dst_spread:.4f} mm"
    assert conv_spread > factor * dst_spread, f"conventional {conv_spread:.4f} mm vs DST {dst_spread:.4f} mm"


def test_prusaslicers_own_step_import_is_not_its_preset_on_this_occt(hemisphere_meshes):
    """What the report's warning on slicer presets says, shown with the slicer: PrusaSlicer's own
    STEP import (OCCT 7.6) of the hemisphere is another mesh than BRepMesh at its parameters here,
    with about half the triangles and a smaller largest chord_dev. Should this OCCT ever mesh as the
    slicer does, this fails, and the warning must go."""
    from worker.dst.report import MeshInput, build_report
    from worker.dst.step_io import read_step
    from worker.dst.stl_io import read_stl

    exe = shutil.which("prusa-slicer")
    if exe is None:
        pytest.skip("prusa-slicer is not installed (.ci/run installs it)")
    tmp_path, _, _ = hemisphere_meshes
    step = tmp_path / "hemi.step"
    own = tmp_path / "hemi_prusaslicer_import.stl"
    subprocess.run(
        [exe, "--export-stl", "--output", str(own), str(step)],
        check=True,
        capture_output=True,
        timeout=300,
        env={**os.environ, "HOME": str(tmp_path)},
    )
    v, t = read_stl(own)
    report = build_report(
        read_step(step),
        SliceParams(layer_height=0.2),
        file_name=str(step),
        meshes=[MeshInput("own", "input", v, t)],
        baselines=["prusaslicer"],
    )
    by_name = {m.name: m for m in report.meshes}
    mine, preset = by_name["own"], by_name["prusaslicer"]
    assert mine.triangles < 0.7 * preset.triangles, (mine.triangles, preset.triangles)
    assert mine.summary.max_chord_dev < 0.9 * preset.summary.max_chord_dev
    # both are meshes of the same hemisphere, placed alike: the slicer's is no worse than 0.03 mm
    assert mine.summary.max_chord_dev < 0.03 and mine.summary.max_perimeter_err < 0.01
    assert any(w.startswith("baseline(s) prusaslicer are made with") for w in report.warnings)
    assert "PrusaSlicer itself links OCCT 7.6.1" in preset.description
