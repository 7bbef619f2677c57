"""Job artifacts where every API and worker process reaches them: a directory (local disk or a shared
mount), or any fsspec URL (``s3://bucket/prefix``) with a machine-local scratch directory.

Layout: ``<root>/<job id>/{input.step, mesh.stl, report.json, report.html, plot.svg, plot.png}``.
A job runs in its local directory (``job_dir``); ``publish`` then makes its files visible (a no-op on
a directory store, an upload on a remote one). Local files are written under a temporary name and
renamed, so a reader never sees a partial artifact; remote objects appear whole when uploaded.
"""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path
from typing import Any, BinaryIO

ARTIFACTS = {
    "mesh": ("mesh.stl", "model/stl"),
    "report": ("report.json", "application/json"),
    "report_html": ("report.html", "text/html; charset=utf-8"),
    "plot_svg": ("plot.svg", "image/svg+xml"),
    "plot_png": ("plot.png", "image/png"),
}
INPUT_NAME = "input.step"


def _check_id(job_id: str) -> str:
    if not job_id.isalnum():  # ids are hex: never a path
        raise ValueError("bad job id")
    return job_id


class ArtifactStore:
    """Artifacts in a directory (local, or a mount every machine shares)."""

    remote = False

    def __init__(self, root: Path):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)

    def job_dir(self, job_id: str) -> Path:
        """The job's local working directory (where it runs and writes its files)."""
        return self.root / _check_id(job_id)

    def path(self, job_id: str, name: str) -> Path:
        return self.job_dir(job_id) / name

    def input_path(self, job_id: str) -> Path:
        return self.path(job_id, INPUT_NAME)

    def save_input(self, job_id: str, src: Path) -> None:
        d = self.job_dir(job_id)
        d.mkdir(parents=True, exist_ok=True)
        tmp = d / f".{INPUT_NAME}.part"
        shutil.copyfile(src, tmp)
        os.replace(tmp, d / INPUT_NAME)

    def fetch_input(self, job_id: str) -> Path:
        """The input as a local file, for the job to read."""
        return self.input_path(job_id)

    def publish(self, job_id: str) -> dict[str, dict[str, Any]]:
        """Make the job's artifacts visible to every reader; returns their manifest."""
        return self.manifest(job_id)

    def manifest(self, job_id: str) -> dict[str, dict[str, Any]]:
        """name -> {file, size, sha256, media_type} of the artifacts present in the job's directory."""
        out = {}
        for name, (file, media) in ARTIFACTS.items():
            p = self.path(job_id, file)
            if p.is_file():
                out[name] = {
                    "file": file,
                    "size": p.stat().st_size,
                    "sha256": sha256_file(p),
                    "media_type": media,
                }
        return out

    def exists(self, job_id: str, file: str) -> bool:
        return self.path(job_id, file).is_file()

    def open(self, job_id: str, file: str) -> BinaryIO:
        return open(self.path(job_id, file), "rb")

    def remove(self, job_id: str) -> None:
        shutil.rmtree(self.job_dir(job_id), ignore_errors=True)

    def ping(self) -> None:
        if not self.root.is_dir():
            raise OSError(f"artifact directory {self.root} is missing")


class RemoteArtifactStore(ArtifactStore):
    """Artifacts under an fsspec URL (``s3://bucket/prefix``, ``gcs://...``); jobs run in a local scratch
    directory and their files are uploaded when they finish."""

    remote = True

    def __init__(self, url: str, scratch: Path, options: dict[str, Any] | None = None):
        import fsspec  # noqa: PLC0415 - only remote stores need it

        super().__init__(scratch)
        self.url = url
        self.fs, self.prefix = fsspec.core.url_to_fs(url, **(options or {}))
        self.prefix = self.prefix.rstrip("/")

    def _key(self, job_id: str, name: str) -> str:
        return f"{self.prefix}/{_check_id(job_id)}/{name}"

    def _put(self, src: Path, key: str) -> None:
        self.fs.makedirs(key.rsplit("/", 1)[0], exist_ok=True)  # directories for file-like filesystems
        self.fs.put_file(str(src), key)

    def save_input(self, job_id: str, src: Path) -> None:
        self._put(src, self._key(job_id, INPUT_NAME))

    def fetch_input(self, job_id: str) -> Path:
        local = self.input_path(job_id)
        local.parent.mkdir(parents=True, exist_ok=True)
        tmp = local.with_name(f".{INPUT_NAME}.part")
        self.fs.get_file(self._key(job_id, INPUT_NAME), str(tmp))
        os.replace(tmp, local)
        return local

    def publish(self, job_id: str) -> dict[str, dict[str, Any]]:
        manifest = self.manifest(job_id)
        for meta in manifest.values():
            self._put(self.path(job_id, meta["file"]), self._key(job_id, meta["file"]))
        shutil.rmtree(self.job_dir(job_id), ignore_errors=True)  # the scratch copy is no longer needed
        return manifest

    def exists(self, job_id: str, file: str) -> bool:
        key = self._key(job_id, file)
        self.fs.invalidate_cache(key.rsplit("/", 1)[0])  # another process may have written it since
        return bool(self.fs.exists(key))

    def open(self, job_id: str, file: str) -> BinaryIO:
        return self.fs.open(self._key(job_id, file), "rb")

    def remove(self, job_id: str) -> None:
        key = f"{self.prefix}/{_check_id(job_id)}"
        self.fs.invalidate_cache(key)
        if self.fs.exists(key):
            self.fs.rm(key, recursive=True)
        shutil.rmtree(self.job_dir(job_id), ignore_errors=True)

    def ping(self) -> None:
        self.fs.ls(self.prefix.split("/")[0] if "/" in self.prefix else self.prefix)


def make_artifact_store(settings) -> ArtifactStore:
    if settings.artifact_url:
        return RemoteArtifactStore(
            settings.artifact_url, settings.effective_artifact_dir, settings.artifact_options
        )
    return ArtifactStore(settings.effective_artifact_dir)


def sha256_file(path: Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()
