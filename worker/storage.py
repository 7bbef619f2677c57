"""Job artifacts on a directory every API and worker process reaches (local disk, or a shared mount).

Layout: ``<artifact_dir>/<job id>/{input.step, mesh.stl, report.json, report.html, plot.svg, plot.png}``.
Files are written under a temporary name and renamed, so a reader never sees a partial artifact.
"""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

ARTIFACTS = {
    "mesh": ("mesh.stl", "model/stl"),
    "report": ("report.json", "application/json"),
    "report_html": ("report.html", "text/html; charset=utf-8"),
    "plot_svg": ("plot.svg", "image/svg+xml"),
    "plot_png": ("plot.png", "image/png"),
}
INPUT_NAME = "input.step"


class ArtifactStore:
    def __init__(self, root: Path):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)

    def job_dir(self, job_id: str) -> Path:
        if not job_id.isalnum():  # ids are hex: never a path
            raise ValueError("bad job id")
        return self.root / job_id

    def path(self, job_id: str, name: str) -> Path:
        return self.job_dir(job_id) / name

    def input_path(self, job_id: str) -> Path:
        return self.path(job_id, INPUT_NAME)

    def save_input(self, job_id: str, src: Path) -> Path:
        d = self.job_dir(job_id)
        d.mkdir(parents=True, exist_ok=True)
        dst = d / INPUT_NAME
        tmp = d / f".{INPUT_NAME}.part"
        shutil.copyfile(src, tmp)
        os.replace(tmp, dst)
        return dst

    def remove(self, job_id: str) -> None:
        shutil.rmtree(self.job_dir(job_id), ignore_errors=True)

    def manifest(self, job_id: str) -> dict[str, dict]:
        """name -> {file, size, sha256, media_type} of the artifacts present."""
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


def sha256_file(path: Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()
