"""The ``dst`` console script, run as a user runs it."""

from __future__ import annotations

import os
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


def test_slice_in_the_print_orientation_asked_for(make_step, tmp_path):
    """A 6 mm wide, 4 mm tall cone laid on its side (90 degrees about y: its axis along x, the tip
    towards +x) is 12 mm tall, its tip at x = 4."""
    out = tmp_path / "side.stl"
    res = run_dst(
        "slice", str(make_step("cone", radius=6, height=4)), "-o", str(out), "--rotate-y", "90", "-q"
    )
    assert res.returncode == 0, res.stderr
    mesh = trimesh.load(out, file_type="stl")
    assert mesh.is_watertight
    # (the tip and the widest line lie between planes 5.9 and 6.1: the rings there come within 0.07 mm)
    np.testing.assert_allclose(mesh.bounds, [[0.0, -6.0, 0.0], [4.0, 6.0, 12.0]], atol=0.07)


def test_3mf_output_by_extension(make_step, tmp_path):
    out = tmp_path / "part.3mf"
    step = make_step("cone", radius=3, height=2)
    res = run_dst("slice", str(step), "-o", str(out), "-q")
    assert res.returncode == 0, res.stderr
    mesh = trimesh.load(out, file_type="3mf", force="mesh")
    assert mesh.is_watertight and mesh.bounds[0][2] == 0.0
    res = run_dst("slice", str(step), "-o", str(tmp_path / "b.3mf"), "--ascii")
    assert res.returncode == 1 and "--ascii is for STL" in res.stderr
    assert not (tmp_path / "b.3mf").exists()


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
        (["--rotate-x", "720"], "rotate_x must be between -360 and 360 degrees, got 720.0"),
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
        "--rotate-x",
        "--rotate-y",
        "--rotate-z",
        "--ascii",
    ):
        assert opt in res.stdout


def test_slice_with_report_html_and_plot(make_step, tmp_path):
    import json

    step = make_step("cone", radius=6, height=4)
    out, rep, html, svg = (tmp_path / n for n in ("p.stl", "r.json", "r.html", "p.svg"))
    res = run_dst(
        "slice",
        str(step),
        "-o",
        str(out),
        "--report",
        str(rep),
        "--html",
        str(html),
        "--plot",
        str(svg),
        "--baselines",
        "occt_fast",
    )
    assert res.returncode == 0, res.stderr
    report = json.loads(rep.read_text())
    assert [m["name"] for m in report["meshes"]] == ["dst", "occt_fast"]
    assert len(report["meshes"][0]["layers"]) == len(report["planes"]) == 20
    assert "max vertex_dev" in res.stderr  # the summary table
    assert html.read_text().count("<svg") == 1 and svg.read_text().lstrip().startswith("<?xml")


def test_report_measures_a_users_mesh(make_step, tmp_path):
    """`dst report` on a coarse OCCT export: measured, and far worse than DST's own mesh would be."""
    import json

    from OCP.BRepMesh import BRepMesh_IncrementalMesh
    from OCP.StlAPI import StlAPI_Writer

    from worker.dst.step_io import read_step

    step = make_step("hemisphere", radius=8)
    part = read_step(step)
    BRepMesh_IncrementalMesh(part.compound, 0.2, False, 0.5, False)
    export = tmp_path / "export.stl"
    writer = StlAPI_Writer()
    writer.ASCIIMode = True
    assert writer.Write(part.compound, str(export))
    rep = tmp_path / "r.json"
    res = run_dst("report", str(step), str(export), "-o", str(rep), "--baselines", "none", "-q")
    assert res.returncode == 0, res.stderr
    (m,) = json.loads(rep.read_text())["meshes"]
    assert m["name"] == "export.stl" and m["kind"] == "input"
    assert m["summary"]["max_vertex_dev"] > 0.05


@pytest.mark.parametrize(
    ("extra", "code", "needle"),
    [
        (["--baselines", "nonsense", "--report", "r.json"], 2, "unknown baseline"),
        (["--baselines", "occt_fast"], 1, "need --report"),
        (["--plot", "x.gif", "--report", "r.json"], 1, ".svg or .png"),
        (["--html", "r.html"], 1, "need --report"),
        (["--processes", "0", "--report", "r.json"], 2, "from 1 to 256"),
        (["--processes", "2"], 1, "need --report"),
    ],
)
def test_report_option_errors(make_step, tmp_path, extra, code, needle):
    args = ["slice", str(make_step("cone", radius=3, height=2)), "-o", str(tmp_path / "p.stl")]
    res = run_dst(*args, *[str(tmp_path / e) if e.endswith((".json", ".gif", ".html")) else e for e in extra])
    assert res.returncode == code, res.stderr
    assert needle in res.stderr


def test_report_refuses_a_file_that_is_not_stl(make_step, tmp_path):
    bad = tmp_path / "bad.stl"
    bad.write_bytes(b"this is not a mesh at all" * 10)
    res = run_dst(
        "report", str(make_step("cone", radius=3, height=2)), str(bad), "-o", str(tmp_path / "r.json")
    )
    assert res.returncode == 1 and "mesh_read_error" in res.stderr


def test_a_worker_shares_the_cpus_between_its_jobs_reports(monkeypatch):
    from worker import cli
    from worker.dst.forked import usable_cpus

    monkeypatch.delenv("DST_REPORT_PROCESSES", raising=False)
    cli._share_cpus_between_jobs(2)
    assert os.environ["DST_REPORT_PROCESSES"] == str(max(1, usable_cpus() // 2))
    monkeypatch.setenv("DST_REPORT_PROCESSES", "7")  # the operator's own setting wins
    cli._share_cpus_between_jobs(2)
    assert os.environ["DST_REPORT_PROCESSES"] == "7"


class _ServiceWhoseReportFailed:
    """``app.client.DstClient`` against a service whose job built its mesh but not its report."""

    downloads: list[str] = []

    def __init__(self, url: str):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def submit(self, path, **params):
        return {"id": "0" * 32, "reused": False}

    def events(self, job_id):
        yield "end", {"progress": 1.0, "stage": "done"}

    def wait(self, job_id):
        error = {"code": "resource_limit", "message": "the reference would cut 12,000,000 pairs"}
        return {"id": job_id, "status": "succeeded", "result": {"warnings": [], "report_error": error}}

    def download_mesh(self, job_id, path):
        self.downloads.append("mesh")
        with open(path, "wb") as fh:
            fh.write(b"solid x\n")

    def download(self, job_id, artifact, path):
        self.downloads.append(artifact)  # the service would answer 404 report_failed


@pytest.mark.parametrize(("report", "code"), [(True, 1), (False, 0)])
def test_remote_writes_the_mesh_of_a_job_whose_report_failed_and_says_why(
    monkeypatch, tmp_path, capsys, report, code
):
    import app.client
    from worker import cli

    monkeypatch.setattr(app.client, "DstClient", _ServiceWhoseReportFailed)
    monkeypatch.setattr(_ServiceWhoseReportFailed, "downloads", [])
    step = tmp_path / "p.step"
    step.write_text("ISO-10303-21;")
    args = [
        "remote",
        str(step),
        "-o",
        str(tmp_path / "p.stl"),
        *(["--report", str(tmp_path / "r.json")] if report else []),
    ]
    assert cli.main(args) == code
    err = capsys.readouterr().err
    assert (tmp_path / "p.stl").read_bytes() == b"solid x\n"
    assert _ServiceWhoseReportFailed.downloads == ["mesh"]  # the missing report is not asked for
    assert "resource_limit" in err and "12,000,000 pairs" in err
    assert ("error [report_failed]" in err) == report  # asked for: an error; else a warning
    assert not (tmp_path / "r.json").exists()
