"""The API alone (no worker): uploads, validation, errors, reuse, listing, deletion.

The queue is replaced by a list, and a job's outcome is written into the store the way a worker
writes it, so each response can be checked without running OCCT.
"""

from __future__ import annotations

import hashlib
import json
import time

import pytest
from fastapi.testclient import TestClient

STEP_HEAD = (
    b"ISO-10303-21;\nHEADER;\nFILE_DESCRIPTION((''),'2;1');\nENDSEC;\nDATA;\nENDSEC;\nEND-ISO-10303-21;\n"
)


@pytest.fixture
def api(tmp_path, monkeypatch):
    monkeypatch.setenv("DST_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("DST_MAX_UPLOAD_MB", "0.05")
    from worker.settings import get_settings

    get_settings.cache_clear()
    from app.main import app

    queued: list[str] = []
    with TestClient(app) as client:
        app.state.enqueue = queued.append
        client.queued = queued
        client.store = app.state.store
        client.artifacts = app.state.artifacts
        yield client
    get_settings.cache_clear()


def upload(api, data: bytes = STEP_HEAD, name: str = "part.step", url: str = "/v1/jobs", **fields):
    return api.post(
        url, files={"file": (name, data, "application/step")}, data={k: str(v) for k, v in fields.items()}
    )


def finish(api, job_id: str, mesh: bytes = b"solid x\n") -> None:
    """Write the job's outcome as a worker does."""
    d = api.artifacts.job_dir(job_id)
    (d / "mesh.stl").write_bytes(mesh)
    (d / "report.json").write_text('{"version": "1.0"}')
    api.store.update(
        job_id,
        status="succeeded",
        progress=1.0,
        stage="done",
        finished_at=time.time(),
        artifacts=api.artifacts.manifest(job_id),
        result={"triangles": 12, "warnings": ["w"]},
    )


def test_upload_creates_a_queued_job(api):
    r = upload(api, layer_height=0.1, mode="inclusive", target_slicer="cura", baselines="occt_fast")
    assert r.status_code == 201
    job = r.json()
    assert r.headers["location"] == f"/v1/jobs/{job['id']}"
    assert job["status"] == "queued" and job["progress"] == 0.0
    assert job["params"]["layer_height"] == 0.1 and job["params"]["mode"] == "inclusive"
    assert job["params"]["baselines"] == ["occt_fast"]
    assert job["file_sha256"] == hashlib.sha256(STEP_HEAD).hexdigest()
    assert api.queued == [job["id"]]
    assert api.artifacts.input_path(job["id"]).read_bytes() == STEP_HEAD
    assert api.get(f"/v1/jobs/{job['id']}").json()["status"] == "queued"


def test_same_file_and_parameters_reuse_the_job(api):
    first = upload(api).json()
    again = upload(api, name="renamed.stp")
    assert again.status_code == 200 and again.json()["id"] == first["id"] and again.json()["reused"]
    other = upload(api, layer_height=0.3)
    assert other.status_code == 201 and other.json()["id"] != first["id"]
    finish(api, first["id"])
    assert upload(api).json()["id"] == first["id"]  # a finished result is reused too
    assert api.queued == [first["id"], other.json()["id"]]


def test_the_print_orientation_is_a_job_parameter(api):
    """A turned part is another job (another mesh); no turn, or a turn of 0, is the same job as one
    submitted before the parameter existed (its reuse key leaves the turn out)."""
    plain = upload(api).json()
    assert plain["params"]["rotate_x"] == plain["params"]["rotate_y"] == plain["params"]["rotate_z"] == 0
    zero = upload(api, rotate_x=0, rotate_y=0.0, rotate_z=-0.0)
    assert zero.status_code == 200 and zero.json()["id"] == plain["id"]
    turned = upload(api, rotate_y=-90)
    assert turned.status_code == 201 and turned.json()["params"]["rotate_y"] == -90
    legacy_key = hashlib.sha256(
        (plain["file_sha256"] + json.dumps(_without_rotation(plain["params"]), sort_keys=True)).encode()
    ).hexdigest()
    assert api.store.find_reusable(legacy_key).id == plain["id"]
    assert api.queued == [plain["id"], turned.json()["id"]]


def test_every_slicing_field_is_a_form_field_and_a_job_parameter_with_the_cores_bounds(api):
    """The API's form and job schema are written out for FastAPI and the OpenAPI spec; they must
    carry every field of the core's SliceParams, with the same bounds (a new field left out would
    be silently dropped, a looser bound accepted here and refused by the worker)."""
    import inspect

    from app.main import UploadForm
    from app.schemas import JobParams
    from worker.dst.params import SLICING_FIELDS, SliceParams

    assert set(SLICING_FIELDS) <= set(inspect.signature(UploadForm).parameters)
    assert set(JobParams.model_fields) == {*SLICING_FIELDS, "baselines"}

    def bounds(field) -> tuple:
        return tuple(
            next((getattr(m, k) for m in field.metadata if hasattr(m, k)), None) for k in ("ge", "le")
        )

    for name in SLICING_FIELDS:
        assert bounds(JobParams.model_fields[name]) == bounds(SliceParams.model_fields[name]), name
    # every one of them reaches the job
    job = upload(api, **{"first_layer_height": 0.3, "target_slicer": "prusa", "rotate_z": 15}).json()
    assert set(job["params"]) == {*SLICING_FIELDS, "baselines"}
    assert job["params"]["first_layer_height"] == 0.3 and job["params"]["rotate_z"] == 15


def _without_rotation(params: dict) -> dict:
    return {k: v for k, v in params.items() if not k.startswith("rotate_")}


@pytest.mark.parametrize(
    ("data", "fields", "status", "code"),
    [
        (b"solid cube\nfacet normal 0 0 1\n", {}, 422, "not_step"),
        (b"", {}, 422, "not_step"),
        (STEP_HEAD, {"layer_height": 5}, 422, "invalid_parameters"),
        (STEP_HEAD, {"chord_error": 0.9, "segment_length": 0.5}, 422, "invalid_parameters"),
        (STEP_HEAD, {"mode": "sideways"}, 422, "invalid_parameters"),
        (STEP_HEAD, {"mode": "inclusive", "target_slicer": "prusa"}, 422, "invalid_parameters"),
        (STEP_HEAD, {"baselines": "occt_fast,bogus"}, 422, "invalid_parameters"),
        (STEP_HEAD, {"rotate_x": 400}, 422, "invalid_parameters"),
        (STEP_HEAD, {"rotate_y": "sideways"}, 422, "invalid_parameters"),
        (STEP_HEAD + b"x" * 60_000, {}, 413, "upload_too_large"),
    ],
)
def test_bad_uploads_get_specific_errors(api, data, fields, status, code):
    r = upload(api, data, **fields)
    assert r.status_code == status, r.text
    assert r.json()["error"]["code"] == code
    assert r.json()["error"]["message"]
    assert api.queued == [] and api.store.list(limit=10, offset=0)[1] == 0


def test_oversized_upload_refused_from_its_header(api):
    r = api.post(
        "/v1/jobs",
        content=b"x" * 10,
        headers={"content-length": str(50_000_000), "content-type": "multipart/form-data; boundary=x"},
    )
    assert r.status_code == 413 and r.json()["error"]["code"] == "upload_too_large"


def test_missing_file_field(api):
    r = api.post("/v1/jobs", data={"layer_height": "0.2"})
    assert r.status_code == 422 and r.json()["error"]["code"] == "missing_file"


def test_unknown_job_and_artifacts_before_they_exist(api):
    assert api.get("/v1/jobs/" + "0" * 32).json()["error"]["code"] == "job_not_found"
    assert api.get("/v1/jobs/nonsense").status_code == 404
    job = upload(api).json()
    r = api.get(f"/v1/jobs/{job['id']}/mesh")
    assert r.status_code == 409 and r.json()["error"]["code"] == "mesh_not_ready"
    assert api.get(f"/v1/jobs/{job['id']}/report").status_code == 409


def test_finished_job_serves_its_artifacts_with_etag_and_ranges(api):
    job = upload(api, name="../../my part?.STEP").json()
    assert job["file_name"] == "my_part_.STEP"
    body = b"solid dst\n" + bytes(range(256)) * 10
    finish(api, job["id"], body)
    got = api.get(f"/v1/jobs/{job['id']}").json()
    assert got["status"] == "succeeded" and got["links"]["mesh"].endswith("/mesh")
    assert got["result"]["triangles"] == 12
    r = api.get(f"/v1/jobs/{job['id']}/mesh")
    assert r.status_code == 200 and r.content == body
    assert r.headers["content-length"] == str(len(body))
    assert r.headers["content-disposition"] == 'attachment; filename="my_part_.stl"'
    etag = r.headers["etag"]
    assert etag == f'"{hashlib.sha256(body).hexdigest()}"'
    assert api.get(f"/v1/jobs/{job['id']}/mesh", headers={"if-none-match": etag}).status_code == 304
    part = api.get(f"/v1/jobs/{job['id']}/mesh", headers={"range": "bytes=10-19"})
    assert part.status_code == 206 and part.content == body[10:20]
    assert api.get(f"/v1/jobs/{job['id']}/report").json() == {"version": "1.0"}
    assert api.get(f"/v1/jobs/{job['id']}/plot.svg").status_code == 404  # not produced here


def test_failed_job_reports_why(api):
    job = upload(api).json()
    api.store.update(job["id"], status="failed", error_code="not_a_solid", error_message="no closed solid")
    got = api.get(f"/v1/jobs/{job['id']}").json()
    assert got["error"] == {"code": "not_a_solid", "message": "no closed solid"}
    r = api.get(f"/v1/jobs/{job['id']}/mesh")
    assert r.status_code == 409 and "not_a_solid" in r.json()["error"]["message"]
    # a failed job is not reused: the same upload queues a new one
    assert upload(api).status_code == 201


def test_a_job_whose_report_failed_serves_its_mesh_and_says_why_there_is_no_report(api):
    job = upload(api).json()
    d = api.artifacts.job_dir(job["id"])
    (d / "mesh.stl").write_bytes(b"solid x\n")
    api.store.update(
        job["id"],
        status="succeeded",
        progress=1.0,
        stage="done",
        finished_at=time.time(),
        artifacts=api.artifacts.manifest(job["id"]),
        result={"triangles": 12, "report_error": {"code": "timeout", "message": "ran past 900 s"}},
    )
    got = api.get(f"/v1/jobs/{job['id']}").json()
    assert got["status"] == "succeeded" and got["error"] is None
    assert got["result"]["report_error"] == {"code": "timeout", "message": "ran past 900 s"}
    assert got["links"]["mesh"].endswith("/mesh") and got["links"]["report"] is None
    assert api.get(f"/v1/jobs/{job['id']}/mesh").content == b"solid x\n"
    for artifact in ("report", "report.html", "plot.svg", "plot.png"):
        r = api.get(f"/v1/jobs/{job['id']}/{artifact}")
        err = r.json()["error"]
        assert r.status_code == 404 and err["code"] == "report_failed"
        assert "timeout: ran past 900 s" in err["message"] and f"/v1/jobs/{job['id']}/mesh" in err["message"]


def test_list_is_paginated_newest_first(api):
    ids = [upload(api, layer_height=0.1 + 0.01 * i).json()["id"] for i in range(5)]
    page = api.get("/v1/jobs", params={"limit": 2}).json()
    assert [j["id"] for j in page["jobs"]] == ids[::-1][:2]
    assert page["total"] == 5 and page["next"] == "/v1/jobs?limit=2&offset=2"
    last = api.get("/v1/jobs", params={"limit": 2, "offset": 4}).json()
    assert [j["id"] for j in last["jobs"]] == [ids[0]] and last["next"] is None
    assert api.get("/v1/jobs", params={"limit": 500}).status_code == 422


def test_delete_cancels_and_removes(api):
    job = upload(api).json()
    d = api.artifacts.job_dir(job["id"])
    assert d.is_dir()
    assert api.delete(f"/v1/jobs/{job['id']}").status_code == 204
    assert not d.exists()
    assert api.get(f"/v1/jobs/{job['id']}").status_code == 404
    assert api.delete(f"/v1/jobs/{job['id']}").status_code == 404


def test_events_end_with_the_finished_job(api):
    job = upload(api).json()
    finish(api, job["id"])
    with api.stream("GET", f"/v1/jobs/{job['id']}/events") as r:
        text = r.read().decode()
    assert r.headers["content-type"].startswith("text/event-stream")
    assert "event: end" in text and '"status":"succeeded"' in text


def test_health_and_page(api):
    assert api.get("/health").json() == {"status": "ok"}
    assert "dst-service" in api.get("/").text
    ready = api.get("/ready")
    assert ready.status_code == 503 and ready.json()["workers"] == 0  # no worker in this test


def test_unknown_paths_and_methods_get_the_api_error_format_with_every_allowed_method(api):
    """Routing errors come from the framework's router, not from a route: they too are
    ``{"error": {"code", "message"}}`` (``not_found``, ``method_not_allowed``), and a 405 names in
    its ``Allow`` header every method the resource has (GET and POST on /v1/jobs, served by two
    routes), as RFC 9110 asks."""
    r = api.get("/v2/jobs")
    assert r.status_code == 404 and r.json()["error"]["code"] == "not_found", r.text
    r = api.put("/v1/jobs")
    assert r.status_code == 405 and r.json()["error"]["code"] == "method_not_allowed", r.text
    assert {m.strip() for m in r.headers["allow"].split(",")} == {"GET", "POST"}
    r = api.post("/v1/jobs/" + "0" * 64)
    assert r.status_code == 405 and r.json()["error"]["code"] == "method_not_allowed", r.text
    assert {m.strip() for m in r.headers["allow"].split(",")} == {"GET", "DELETE"}
    r = api.get("/v1/slice")
    assert r.status_code == 405 and r.headers["allow"] == "POST"
