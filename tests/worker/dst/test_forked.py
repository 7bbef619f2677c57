"""Forked helper tasks: results and errors come back, dead children are reported, the limit holds."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

from tests.conftest import process_dead
from worker.dst.errors import TessellationError
from worker.dst.forked import TaskDied, TaskGroup, fork_available, idle_cores, usable_cpus

needs_fork = pytest.mark.skipif(not fork_available(), reason="fork is used on Linux only")


def _pid_and_sum(a: np.ndarray) -> tuple[int, float]:
    return os.getpid(), float(a.sum())


def _fail() -> None:
    raise TessellationError("the face has no triangles")


def _die() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def _span(seconds: float) -> tuple[float, float]:
    t = time.monotonic()
    time.sleep(seconds)
    return t, time.monotonic()


@needs_fork
def test_a_forked_task_sees_the_parents_memory_and_returns_its_value():
    big = np.arange(1_000_000, dtype=np.float64)  # not pickled on the way in: the child shares it
    with TaskGroup(forked=True) as tasks:
        t = tasks.submit(_pid_and_sum, big)
        pid, total = t.result()
    assert pid != os.getpid()
    assert total == float(big.sum())


@pytest.mark.parametrize("forked", [True, False])
def test_errors_come_back_with_their_type_and_code(forked):
    if forked and not fork_available():
        pytest.skip("fork is used on Linux only")
    with TaskGroup(forked=forked) as tasks:
        t = tasks.submit(_fail)
        with pytest.raises(TessellationError, match="no triangles") as info:
            t.result()
    assert info.value.code == "tessellation_error"
    if forked:
        assert any("forked helper" in n for n in info.value.__notes__)


@needs_fork
def test_a_child_that_dies_is_reported_not_waited_for():
    with TaskGroup(forked=True) as tasks:
        t = tasks.submit(_die)
        with pytest.raises(TaskDied, match="signal 9"):
            t.result()


@needs_fork
def test_no_more_children_than_the_limit_run_at_once():
    with TaskGroup(forked=True, limit=2) as tasks:
        spans = [t.result() for t in [tasks.submit(_span, 0.3) for _ in range(5)]]
    events = sorted([(a, 1) for a, _ in spans] + [(b, -1) for _, b in spans])
    running = np.cumsum([e for _, e in events])
    assert running.max() == 2  # two at a time, and five ran


@needs_fork
def test_leaving_the_group_early_kills_its_children():
    with pytest.raises(RuntimeError), TaskGroup(forked=True) as tasks:
        t = tasks.submit(_span, 60.0)
        raise RuntimeError("the computation failed")
    with pytest.raises(ProcessLookupError):
        os.kill(t.pid, 0)  # killed and reaped


@needs_fork
def test_a_niced_task_runs_at_a_lower_priority_and_leaves_this_process_as_it_was():
    mine = os.nice(0)
    with TaskGroup(forked=True) as tasks:
        theirs = tasks.submit(os.nice, 0, nice=5).result()
    assert theirs == min(mine + 5, 19)
    assert os.nice(0) == mine


@needs_fork
def test_children_that_sent_their_results_are_reaped_by_the_end_of_the_group():
    """A child's result is taken without waiting for it to exit; by the group's end every child has
    been reaped (no zombies left behind)."""
    with TaskGroup(forked=True, limit=2) as tasks:
        pids = [t.result()[0] for t in [tasks.submit(_pid_and_sum, np.ones(3)) for _ in range(5)]]
    for pid in pids:
        with pytest.raises(ChildProcessError):
            os.waitpid(pid, os.WNOHANG)


def _stream(marker: str, big: int):
    """Yield a value larger than a pipe holds and the time right after; then wait (up to 20 s) for
    the parent to say it has the first value; return whether it did."""
    yield np.arange(big, dtype=np.float64)
    yield time.monotonic()
    deadline = time.monotonic() + 20.0
    while not os.path.exists(marker) and time.monotonic() < deadline:
        time.sleep(0.01)
    return os.path.exists(marker)


def _stream_then(fail: str):
    yield 1
    yield 2
    if fail == "raise":
        raise TessellationError("the second face has no triangles")
    os.kill(os.getpid(), signal.SIGKILL)


@needs_fork
def test_a_generator_tasks_values_arrive_while_it_works_on_unread():
    """The child yields 8 MB (a pipe holds 64 kB) and goes on at once, without waiting for this
    process to read; this process gets the first value while the child is still running."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp, TaskGroup(forked=True) as tasks:
        marker = os.path.join(tmp, "got-it")
        t = tasks.submit(_stream, marker, 1_000_000)
        time.sleep(0.5)  # not reading
        reading = time.monotonic()
        values = t.items()
        first = next(values)
        assert np.array_equal(first, np.arange(1_000_000, dtype=np.float64))
        assert not t.done()  # the child is waiting for the marker: still running
        open(marker, "w").close()
        after_first = next(values)
        assert after_first < reading  # the child did not wait for this process to read
        assert list(values) == []
        assert t.result() is True


def _two_then_wait(marker: str):
    """Yield two values; then wait (up to 20 s) for the parent's marker and yield a third."""
    yield "first"
    yield "second"
    deadline = time.monotonic() + 20.0
    while not os.path.exists(marker) and time.monotonic() < deadline:
        time.sleep(0.01)
    yield "third"


@needs_fork
def test_the_values_a_running_task_has_sent_are_taken_without_waiting_for_more():
    """``items_ready`` returns what the child has sent so far while it is still at work (the report
    measures the baselines already made together); ``items`` then gives only the rest."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp, TaskGroup(forked=True) as tasks:
        marker = os.path.join(tmp, "go-on")
        t = tasks.submit(_two_then_wait, marker)
        got: list[str] = []
        deadline = time.monotonic() + 20.0
        while len(got) < 2 and time.monotonic() < deadline:
            got += t.items_ready()  # never blocks: the child waits for the marker after two
            time.sleep(0.01)
        assert got == ["first", "second"]
        assert not t.done() and t.items_ready() == []
        open(marker, "w").close()
        assert list(t.items()) == ["third"]
        t.result()


@needs_fork
def test_waiting_for_news_does_not_wait_for_values_already_read():
    """``free`` reads what the children have sent; ``wait_any`` then returns at once for values no
    one has taken yet, rather than waiting for the child's next message (here: 20 s away)."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp, TaskGroup(forked=True) as tasks:
        t = tasks.submit(_two_then_wait, os.path.join(tmp, "never"))
        time.sleep(0.5)  # both values sent; the child waits for the marker
        tasks.free()  # reads them

        def waited(*_):
            raise TimeoutError("wait_any waited for news it already had")

        before = signal.signal(signal.SIGALRM, waited)
        signal.alarm(5)
        try:
            tasks.wait_any()
        finally:
            signal.alarm(0)
            signal.signal(signal.SIGALRM, before)
        assert t.items_ready() == ["first", "second"]
        t.kill()


def _wrapped_stream(fail: str):
    return _stream_then(fail)  # not a generator function: returns a generator


@pytest.mark.parametrize(
    ("forked", "fn"), [(True, _stream_then), (False, _stream_then), (True, _wrapped_stream)]
)
def test_a_generator_task_that_fails_gives_its_values_then_its_error(forked, fn):
    """Forked or inline; a function that only returns a generator streams through the pipe."""
    if forked and not fork_available():
        pytest.skip("fork is used on Linux only")
    with TaskGroup(forked=forked) as tasks:
        t = tasks.submit(fn, "raise")
        assert list(t.items()) == [1, 2]
        with pytest.raises(TessellationError, match="second face"):
            t.result()


@needs_fork
def test_a_generator_task_that_dies_gives_its_values_then_task_died():
    with TaskGroup(forked=True) as tasks:
        t = tasks.submit(_stream_then, "die")
        assert list(t.items()) == [1, 2]
        with pytest.raises(TaskDied, match="signal 9"):
            t.result()


def test_inline_tasks_run_in_this_process():
    with TaskGroup(forked=False) as tasks:
        assert not tasks.forked
        pid, _ = tasks.submit(_pid_and_sum, np.ones(3)).result()
    assert pid == os.getpid()


@needs_fork
def test_helpers_die_with_a_killed_job_process():
    """A job process killed for its timeout takes its helpers with it (no orphans running on)."""
    import subprocess
    import sys

    code = (
        "import sys, time\n"
        "from worker.dst.forked import TaskGroup\n"
        "from tests.worker.dst.test_forked import _span\n"
        "with TaskGroup(forked=True) as g:\n"
        "    t = g.submit(_span, 60.0)\n"
        "    print(t.pid, flush=True)\n"
        "    time.sleep(60)\n"
    )
    job = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        helper = int(job.stdout.readline())
        assert not process_dead(helper)
        job.kill()
        job.wait(10)
        deadline = time.monotonic() + 10
        while not process_dead(helper) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert process_dead(helper)
    finally:
        job.kill()


@pytest.mark.skipif(not os.path.exists("/proc/loadavg"), reason="idle cores are read from Linux's /proc")
def test_no_core_is_idle_while_a_busy_process_runs_on_each():
    """``idle_cores`` counts this process as running, so never more than all CPUs but one; with a
    busy process on every CPU (this one waiting), none."""
    assert 0 <= idle_cores() <= usable_cpus() - 1
    busy = []
    try:
        for _ in range(usable_cpus()):
            pid = os.fork()
            if pid == 0:  # spin until killed
                while True:
                    pass
            busy.append(pid)
        time.sleep(0.2)
        assert idle_cores() == 0
    finally:
        for pid in busy:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
