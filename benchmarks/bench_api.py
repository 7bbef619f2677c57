"""Benchmark: API responsiveness while the cores are busy (issue 4: polling a job well under 100 ms p99),
and what a job costs a client beyond its work.

Starts a real `dst serve --workers 2` on a free port, measures GET /v1/jobs/{id} latency on an idle
service (the baseline), then again while two heavy DST jobs run, and prints both with their ratio.
First the hemisphere's job (DST, report with the default baselines, HTML and plots) on a default
`dst serve` (one worker) as a client sees it, submit to succeeded, against the same job's work run in this process (``worker.job.run_job``,
imports done): the difference is the queue, the job's process start, progress and storage.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.conftest import build_part, write_step  # noqa: E402
from tests.service.conftest import Service  # noqa: E402


def latencies(http: httpx.Client, url: str, n: int) -> list[float]:
    out = []
    for _ in range(n):
        t = time.perf_counter()
        r = http.get(url)
        out.append((time.perf_counter() - t) * 1000)
        r.raise_for_status()
        time.sleep(0.01)
    return out


def row(name: str, ms: list[float]) -> str:
    q = statistics.quantiles(ms, n=100)
    return f"{name:28} {statistics.median(ms):8.1f} {q[94]:8.1f} {q[98]:8.1f} {max(ms):8.1f}"


def job_latency(http: httpx.Client, step: Path, tmp: Path, rounds: int = 4) -> None:
    import worker.dst.render  # noqa: F401  (the imports a job's process starts with, done)
    from worker.job import run_job

    here, served = [], []
    for k in range(rounds):
        params = {"layer_height": 0.2 + 0.005 * k}  # a new job each round (same parameters: reused)
        out = tmp / f"inproc{k}"
        out.mkdir()
        t = time.perf_counter()
        run_job(out, step, params, step.name, lambda stage, frac: None)
        here.append(time.perf_counter() - t)
        t = time.perf_counter()
        with open(step, "rb") as fh:
            r = http.post(
                "/v1/jobs", files={"file": (step.name, fh)}, data={k: str(v) for k, v in params.items()}
            )
        r.raise_for_status()
        job = r.json()["id"]
        while (state := http.get(f"/v1/jobs/{job}").json())["status"] not in ("succeeded", "failed"):
            time.sleep(0.2)  # as a client polls (faster polling takes CPU from the job)
        served.append(time.perf_counter() - t)
        assert state["status"] == "succeeded", state
    print(f"{'hemisphere job, s':28} {'rounds':>30} {'median':>8}")
    print(
        f"{'its work in this process':28} {str([round(x, 2) for x in here]):>30} {statistics.median(here):8.2f}"
    )
    print(
        f"{'submit -> succeeded':28} {str([round(x, 2) for x in served]):>30} {statistics.median(served):8.2f}"
    )
    print(f"client's wait / work: {statistics.median(s / h for s, h in zip(served, here, strict=True)):.2f}")


def main() -> None:
    tmp = Path(tempfile.mkdtemp())
    torus = write_step(build_part("torus"), tmp / "torus.step")
    hemisphere = write_step(build_part("hemisphere", radius=20.0), tmp / "hemisphere.step")
    svc = Service(tmp / "data1").start()  # `dst serve`'s default: one job at a time, with every core
    try:
        with httpx.Client(base_url=svc.url, timeout=30) as http:
            job_latency(http, hemisphere, tmp)
    finally:
        svc.stop()
    svc = Service(tmp / "data", args=("--workers", "2")).start()
    try:
        with httpx.Client(base_url=svc.url, timeout=30) as http:

            def submit(seg: float) -> str:
                with open(torus, "rb") as fh:
                    r = http.post(
                        "/v1/jobs",
                        files={"file": ("torus.step", fh)},
                        data={"layer_height": "0.05", "segment_length": str(seg), "chord_error": "0.002"},
                    )
                r.raise_for_status()
                return r.json()["id"]

            probe = submit(0.5)
            while http.get(f"/v1/jobs/{probe}").json()["status"] not in ("succeeded", "failed"):
                time.sleep(0.2)
            idle = latencies(http, f"/v1/jobs/{probe}", 300)
            heavy = [submit(0.1), submit(0.11)]
            while any(http.get(f"/v1/jobs/{h}").json()["status"] != "running" for h in heavy):
                time.sleep(0.1)
            busy = latencies(http, f"/v1/jobs/{heavy[0]}", 300)
            states = [http.get(f"/v1/jobs/{h}").json()["status"] for h in heavy]
        print(f"{'GET /v1/jobs/{id}, ms':28} {'p50':>8} {'p95':>8} {'p99':>8} {'max':>8}")
        print(row("idle service (baseline)", idle))
        print(row("2 heavy jobs on 2 cores", busy))
        print(
            f"p99 busy / idle: {statistics.quantiles(busy, n=100)[98] / statistics.quantiles(idle, n=100)[98]:.2f}"
            f"   (jobs still {states} at the end of the measurement; target p99 < 100 ms)"
        )
    finally:
        svc.stop()


if __name__ == "__main__":
    main()
