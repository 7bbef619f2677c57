"""The ``dst`` console script, run as a user runs it."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import trimesh


def run_dst(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "worker.cli", *args], capture_output=True, text=True, timeout=600
    )


def test_slice_writes_a_binary_stl_and_reports_progress(make_step, tmp_path):
    out = tmp_path / "part.stl"
    res = run_dst(
        "slice", str(make_step("cone", radius=6, height=4)), "-o", str(out), "--layer-height", "0.25"
    )
    assert res.returncode == 0, res.stderr
    assert "reading STEP" in res.stderr and "wrote" in res.stderr
    mesh = trimesh.load(out, file_type="stl")
    assert mesh.is_watertight
    assert mesh.bounds[0][2] == 0.0
    assert np.isclose(out.stat().st_size, 84 + 50 * len(mesh.faces))


def test_ascii_output(make_step, tmp_path):
    out = tmp_path / "part.stl"
    res = run_dst("slice", str(make_step("cone", radius=3, height=2)), "-o", str(out), "--ascii", "-q")
    assert res.returncode == 0, res.stderr
    assert out.read_bytes().startswith(b"solid ")
    assert res.stderr == ""


@pytest.mark.parametrize(
    ("args", "expect"),
    [
        (["--layer-height", "0"], "layer_height must be between 0.01 and 2 mm, got 0.0"),
        (["--layer-height", "50"], "layer_height must be between 0.01 and 2 mm, got 50.0"),
        (["--chord-error", "0"], "chord_error must be between 0.0001 and 1 mm, got 0.0"),
    ],
)
def test_parameters_out_of_range_are_refused_with_the_range(make_step, tmp_path, args, expect):
    out = tmp_path / "part.stl"
    res = run_dst("slice", str(make_step("cone", radius=3, height=2)), "-o", str(out), *args)
    assert res.returncode == 2
    assert expect in res.stderr
    assert "Traceback" not in res.stderr
    assert not out.exists()


@pytest.mark.parametrize(
    ("content", "code"),
    [
        (b"", "step_read_error"),
        (b"solid x\nfacet normal 0 0 1\n", "step_read_error"),
        (b"ISO-10303-21;\nHEADER;\nFILE_DESCRIPTION(('x'),'2;1');\n", "step_read_error"),
    ],
)
def test_bad_input_is_one_line_and_leaves_no_output(tmp_path, content, code):
    src = tmp_path / "bad.step"
    src.write_bytes(content)
    out = tmp_path / "bad.stl"
    res = run_dst("slice", str(src), "-o", str(out), "-q")
    assert res.returncode == 1
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("dst:")]
    assert len(lines) == 1 and f"[{code}]" in lines[0], res.stderr
    assert "Traceback" not in res.stderr
    assert not out.exists() and not (tmp_path / "bad.stl.part").exists()


def test_missing_input_file(tmp_path):
    res = run_dst("slice", str(tmp_path / "nope.step"), "-o", str(tmp_path / "x.stl"))
    assert res.returncode == 1 and "input file not found" in res.stderr


def test_help_lists_the_options():
    res = run_dst("slice", "--help")
    assert res.returncode == 0
    for opt in (
        "--layer-height",
        "--first-layer-height",
        "--mode",
        "--segment-length",
        "--chord-error",
        "--target-slicer",
        "--ascii",
    ):
        assert opt in res.stdout
