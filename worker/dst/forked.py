"""Run functions in forked child processes: a second core for work that the GIL would serialise.

OCCT holds the GIL while it runs, and much of the numpy / scipy work of a report holds it often
enough that two threads get ~1.5 cores. A forked child shares the parent's memory (the part, the
exact reference) without copying or pickling it; only its return value travels back, pickled,
through a pipe.

What may run in a child: numpy / scipy work, and OCCT algorithms that run on the calling thread.
OCCT's thread pool does not survive a fork (its worker threads exist only in the parent): a parallel
OCCT algorithm in the child (``BRepMesh_IncrementalMesh`` with ``isInParallel``) would wait for them
forever. Callers ask OCCT for serial work in a child; ``TaskGroup.forked`` tells them which it is.

Where fork is unavailable or unsafe (anything but Linux: macOS system frameworks are not fork-safe)
or switched off, every task runs inline, at once, in the caller's process.
"""

from __future__ import annotations

import ctypes
import os
import pickle
import select
import signal
import sys
import traceback
from collections.abc import Callable
from typing import Any


class TaskDied(RuntimeError):
    """A child process ended without returning its result (killed, crashed, out of memory)."""


def fork_available() -> bool:
    return sys.platform.startswith("linux") and hasattr(os, "fork")


def usable_cpus() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def die_with_parent() -> None:
    """Linux: have this process killed when its parent dies, however it dies (no orphans left to
    run on after a job's process was killed for its timeout)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
    except OSError:
        return
    pr_set_pdeathsig = 1
    libc.prctl(pr_set_pdeathsig, signal.SIGKILL)
    if os.getppid() == 1:  # the parent died before prctl took effect
        os._exit(1)


class Task:
    """One function call, running in a forked child or already run inline."""

    def __init__(self, fn: Callable[..., Any], args: tuple, forked: bool, nice: int = 0):
        self.pid: int | None = None
        self._fd: int | None = None
        self._outcome: tuple[bool, Any] | None = None
        if not forked:
            try:
                self._outcome = (True, fn(*args))
            except Exception as exc:  # re-raised by result(), where a forked task's would be
                self._outcome = (False, exc)
            return
        r, w = os.pipe()
        pid = os.fork()
        if pid == 0:  # the child: never returns into the caller's code
            try:
                os.close(r)
                die_with_parent()
                if nice:
                    os.nice(nice)
                _run_child(fn, args, w)
            finally:
                os._exit(0)
        os.close(w)
        self.pid, self._fd = pid, r

    @property
    def fileno(self) -> int | None:
        return self._fd

    def done(self) -> bool:
        """The result has been collected (or the task ran inline)."""
        return self._outcome is not None

    def ready(self) -> bool:
        """The result can be collected without waiting (the child has finished its work)."""
        return self.done() or bool(select.select([self._fd], [], [], 0)[0])

    def result(self) -> Any:
        """The function's return value; its exception is raised here."""
        if self._outcome is None:
            self._collect()
        ok, value = self._outcome
        if ok:
            return value
        raise value

    def _collect(self) -> None:
        with os.fdopen(self._fd, "rb") as f:  # the child writes everything, then exits
            data = f.read()
        self._fd = None
        if data:  # the child has sent its result and is exiting: reaped later, not waited for here
            self._outcome = pickle.loads(data)
            _exiting.add(self.pid)
            reap_exited()
            return
        _, status = os.waitpid(self.pid, 0)
        how = (
            f"killed by signal {os.WTERMSIG(status)}"
            if os.WIFSIGNALED(status)
            else f"exit status {os.waitstatus_to_exitcode(status)}"
        )
        self._outcome = (False, TaskDied(f"a helper process ended without a result ({how})"))

    def kill(self) -> None:
        if self._outcome is None and self.pid is not None:
            try:
                os.kill(self.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            self._collect()


# Children that sent their result and are exiting: a large process takes milliseconds to tear down
# its memory, which the parent need not wait for before it starts the next task.
_exiting: set[int] = set()


def reap_exited(*, block: bool = False) -> None:
    """Reap the children that sent their results (those that have exited; ``block``: all)."""
    for pid in list(_exiting):
        try:
            done, _ = os.waitpid(pid, 0 if block else os.WNOHANG)
        except ChildProcessError:  # reaped by someone else
            done = pid
        if done:
            _exiting.discard(pid)


def _run_child(fn: Callable[..., Any], args: tuple, w: int) -> None:
    try:
        outcome: tuple[bool, Any] = (True, fn(*args))
    except BaseException as exc:  # everything goes back to the parent, which raises it
        if not isinstance(exc, MemoryError):  # a note needs memory
            exc.add_note("in a forked helper process:\n" + traceback.format_exc())
        outcome = (False, exc)
    try:
        data = pickle.dumps(outcome, protocol=pickle.HIGHEST_PROTOCOL)
    except Exception as exc:  # an unpicklable result or exception: say what it was
        data = pickle.dumps((False, TaskDied(f"a helper's result could not be sent back: {exc!r}")))
    with os.fdopen(w, "wb") as f:
        f.write(data)


class TaskGroup:
    """Tasks of one computation: at most ``limit`` children at a time; on exit, children still
    running (the computation failed) are killed and reaped.

    ``forked=None`` forks where :func:`fork_available`.
    """

    def __init__(self, *, limit: int | None = None, forked: bool | None = None):
        self.forked = fork_available() if forked is None else (forked and fork_available())
        self.limit = max(1, limit or usable_cpus())
        self._running: list[Task] = []

    def submit(self, fn: Callable[..., Any], *args: Any, nice: int = 0) -> Task:
        """Start ``fn(*args)`` (or, inline, run it); waits while ``limit`` children are busy.
        ``nice``: the child's niceness increment (work that should yield its core to this process)."""
        self._running = [t for t in self._running if not t.done()]  # collected by result()
        while len(self._running) >= self.limit:
            self._wait_one()
        task = Task(fn, args, self.forked, nice)
        if not task.done():
            self._running.append(task)
        return task

    def _wait_one(self) -> None:
        """Block until one running child has finished writing, and collect it."""
        ready, _, _ = select.select([t.fileno for t in self._running], [], [])
        for t in list(self._running):
            if t.fileno in ready:
                t._collect()
                self._running.remove(t)
                return

    def __enter__(self) -> TaskGroup:
        return self

    def __exit__(self, *exc: object) -> None:
        for t in self._running:
            t.kill()  # no-op for those already collected by result()
        self._running.clear()
        reap_exited(block=True)
