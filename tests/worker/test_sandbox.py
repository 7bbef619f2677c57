"""The jobs' processes: forked from a server that imported what a job needs, and nothing else."""

from __future__ import annotations

import os
import sys

import pytest

from worker import sandbox


def _probe(conn) -> None:
    conn.send(([m for m in sandbox.PRELOAD if m in sys.modules], os.getppid()))
    conn.close()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the fork server is Linux-only")
def test_a_jobs_process_starts_with_a_jobs_imports_done_by_the_fork_server():
    ctx = sandbox._context()
    assert ctx.get_start_method() == "forkserver"
    sandbox.warm_up()
    for _ in range(2):  # every job from the same untouched server
        parent, child = ctx.Pipe(duplex=False)
        proc = ctx.Process(target=_probe, args=(child,))
        proc.start()
        child.close()
        loaded, ppid = parent.recv()
        proc.join(30)
        assert proc.exitcode == 0
        assert loaded == list(sandbox.PRELOAD)  # OCCT, scipy, matplotlib: imported before the job
        assert ppid not in (os.getpid(), 1)  # forked by the server, not by this (the worker's) process
