"""A real `dst serve` (and redis-server) on free ports, for end-to-end tests."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from tests.conftest import build_part, write_step
from worker.store import JobStore


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Service:
    """``dst serve`` in its own process group (so a test can kill -9 all of it)."""

    def __init__(self, data_dir: Path, *, env: dict[str, str] | None = None, args: tuple[str, ...] = ()):
        self.data_dir = data_dir
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.env = {**os.environ, "DST_DATA_DIR": str(data_dir), **(env or {})}
        self.args = args
        self.proc: subprocess.Popen | None = None
        self.log = data_dir.parent / f"serve-{self.port}.log"

    def start(self, *, wait_ready: bool = True) -> Service:
        self.data_dir.mkdir(parents=True, exist_ok=True)
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "worker.cli", "serve", "--port", str(self.port), *self.args],
                env=self.env,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        self.wait(ready=wait_ready)
        return self

    def wait(self, *, ready: bool, timeout: float = 90.0) -> None:
        deadline = time.monotonic() + timeout
        path = "/ready" if ready else "/health"
        while time.monotonic() < deadline:
            assert self.proc is not None and self.proc.poll() is None, (
                f"dst serve exited:\n{self.log.read_text()[-3000:]}"
            )
            try:
                if httpx.get(self.url + path, timeout=2).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.3)
        raise AssertionError(f"dst serve not {path} after {timeout} s:\n{self.log.read_text()[-3000:]}")

    def kill9(self) -> None:
        assert self.proc is not None
        os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait(10)

    def stop(self) -> None:
        if self.proc is None or self.proc.poll() is not None:
            return
        os.killpg(self.proc.pid, signal.SIGTERM)
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)

    def store(self) -> JobStore:
        return JobStore(f"sqlite:///{self.data_dir / 'jobs.sqlite'}")


@pytest.fixture(scope="module")
def parts(tmp_path_factory):
    """STEP files of small parts (a 10 mm hemisphere, a tube, a torus), built once per module."""
    d = tmp_path_factory.mktemp("parts")
    return {
        "hemisphere": write_step(build_part("hemisphere", radius=10.0), d / "hemisphere.step"),
        "tube": write_step(build_part("tube"), d / "tube.step"),
        "torus": write_step(build_part("torus"), d / "torus.step"),
    }


@pytest.fixture
def service_factory(tmp_path):
    started: list[Service] = []

    def make(**kw) -> Service:
        s = Service(kw.pop("data_dir", tmp_path / "data"), **kw)
        started.append(s)
        return s

    yield make
    for s in started:
        s.stop()


@pytest.fixture
def redis_url(tmp_path):
    exe = shutil.which("redis-server")
    if exe is None:
        pytest.skip("redis-server is not installed (apt-get install redis-server)")
    port = free_port()
    proc = subprocess.Popen(
        [
            exe,
            "--port",
            str(port),
            "--bind",
            "127.0.0.1",
            "--save",
            "",
            "--appendonly",
            "no",
            "--dir",
            str(tmp_path),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1):
                break
        except OSError:
            time.sleep(0.1)
    yield f"redis://127.0.0.1:{port}/0"
    proc.terminate()
    proc.wait(10)


@pytest.fixture
def s3_bucket():
    """A local S3 (moto's server) with an empty bucket: (fsspec URL, storage options)."""
    exe = shutil.which("moto_server")
    if exe is None:
        pytest.skip("moto_server is not installed (pip install 'moto[server]')")
    s3fs = pytest.importorskip("s3fs")
    port = free_port()
    proc = subprocess.Popen(
        [exe, "-H", "127.0.0.1", "-p", str(port)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    endpoint = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        try:
            httpx.get(endpoint, timeout=1)
            break
        except httpx.HTTPError:
            time.sleep(0.2)
    options = {
        "key": "testing",
        "secret": "testing",
        "client_kwargs": {"endpoint_url": endpoint, "region_name": "us-east-1"},
    }
    boto3 = pytest.importorskip("boto3")
    boto3.client(
        "s3",
        endpoint_url=endpoint,
        aws_access_key_id="testing",
        aws_secret_access_key="testing",
        region_name="us-east-1",
    ).create_bucket(Bucket="dst-test")
    fs = s3fs.S3FileSystem(**options)
    yield "s3://dst-test/artifacts", options, fs
    proc.terminate()
    proc.wait(10)
