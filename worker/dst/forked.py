"""Run functions in forked child processes: a second core for work that the GIL would serialise.

OCCT holds the GIL while it runs, and much of the numpy / scipy work of a report holds it often
enough that two threads get ~1.5 cores. A forked child shares the parent's memory (the part, the
exact reference) without copying or pickling it; only its return value travels back, pickled,
through a pipe.

What may run in a child: numpy / scipy work, and OCCT algorithms that run on the calling thread.
OCCT's thread pool does not survive a fork (its worker threads exist only in the parent): a parallel
OCCT algorithm in the child (``BRepMesh_IncrementalMesh`` with ``isInParallel``) would wait for them
forever. Callers ask OCCT for serial work in a child; ``TaskGroup.forked`` tells them which it is.

A task whose function is a generator sends each value it yields as soon as it is made; the parent
takes them with ``Task.items()`` while the child goes on, then the generator's return value with
``result()``. The values go through a temporary file and only their places through the pipe: a
write to a full pipe would stop the child until its parent reads, and the parent may be busy for
long (a thread of the child writing to the pipe would not help: OCCT holds the GIL while it works).

Where fork is unavailable or unsafe (anything but Linux: macOS system frameworks are not fork-safe)
or switched off, every task runs inline, at once, in the caller's process.
"""

from __future__ import annotations

import ctypes
import inspect
import os
import pickle
import select
import signal
import struct
import sys
import tempfile
import traceback
from collections import deque
from collections.abc import Callable, Iterator
from types import GeneratorType
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


def idle_cores() -> int:
    """How many of this process's CPUs no runnable thread on the machine waits for right now
    (Linux: /proc/loadavg's count of runnable threads, this one included; elsewhere 0). A moment's
    view, for deciding whether a helper would get a core of its own."""
    try:
        with open("/proc/loadavg") as fh:
            runnable = int(fh.read().split()[3].split("/")[0])
    except (OSError, ValueError, IndexError):
        return 0
    return max(0, usable_cpus() - runnable)


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


# Messages from a child: a length (8 bytes) and a pickled (kind, value): values a generator yielded,
# then its outcome, the function's return value or its exception.
_FRAME = struct.Struct("<Q")
_ITEM, _VALUE, _RETURN, _RAISE = 0, 1, 2, 3  # a value: its place in the spool file, or itself
_READ_BYTES = 1 << 20


class Task:
    """One function call, running in a forked child or already run inline."""

    def __init__(self, fn: Callable[..., Any], args: tuple, forked: bool, nice: int = 0):
        self.pid: int | None = None
        self._fd: int | None = None
        self._outcome: tuple[bool, Any] | None = None
        self._items: deque[Any] = deque()  # yielded values not taken yet
        self._buf = bytearray()
        self._spool = None  # a generator's values, written by the child
        if not forked:
            try:
                value = fn(*args)
                if isinstance(value, GeneratorType):
                    value = yield_from(value, self._items.append)
                self._outcome = (True, value)
            except Exception as exc:  # re-raised by result(), where a forked task's would be
                self._outcome = (False, exc)
            return
        if inspect.isgeneratorfunction(fn):
            self._spool = tempfile.TemporaryFile(prefix="dst-task-")  # gone when closed: no leftovers
        r, w = os.pipe()
        pid = os.fork()
        if pid == 0:  # the child: never returns into the caller's code
            try:
                os.close(r)
                die_with_parent()
                if nice:
                    os.nice(nice)
                _run_child(fn, args, w, self._spool)
            finally:
                os._exit(0)
        os.close(w)
        self.pid, self._fd = pid, r

    @property
    def fileno(self) -> int:
        """The pipe from the child (a forked task not collected yet)."""
        assert self._fd is not None
        return self._fd

    @property
    def forked_pid(self) -> int:
        """The child's process id (a forked task)."""
        assert self.pid is not None
        return self.pid

    def done(self) -> bool:
        """The result has been collected (or the task ran inline)."""
        return self._outcome is not None

    def ready(self) -> bool:
        """The result can be collected without waiting (the child has finished its work)."""
        if not self.done():
            self._read(block=False)
        return self.done()

    def result(self) -> Any:
        """The function's return value; its exception is raised here."""
        while self._outcome is None:
            self._read(block=True)
        ok, value = self._outcome
        if ok:
            return value
        raise value

    def items(self) -> Iterator[Any]:
        """A generator function's values, each as soon as the child has sent it (none for a plain
        function). Ends when the child has sent its outcome (or died: ``result()`` says how)."""
        while True:
            while self._items:
                yield self._items.popleft()
            if self._outcome is not None:
                return
            self._read(block=True)

    def items_ready(self) -> list[Any]:
        """The values the child has sent and no one has taken yet, without waiting for more."""
        if not self.done():
            self._read(block=False)
        taken = list(self._items)
        self._items.clear()
        return taken

    def _read(self, *, block: bool) -> None:
        """Take what the child has written: without waiting, or (``block``) until at least one more
        message or its end."""
        while self._outcome is None:
            if not block and not select.select([self.fileno], [], [], 0)[0]:
                return
            chunk = os.read(self.fileno, _READ_BYTES)
            if not chunk:
                self._ended()
                return
            self._buf += chunk
            if self._parse() and block:
                return

    def _parse(self) -> bool:
        """Unpack the whole messages in the buffer; whether there were any."""
        got, pos = False, 0
        while len(self._buf) - pos >= _FRAME.size:
            (n,) = _FRAME.unpack_from(self._buf, pos)
            end = pos + _FRAME.size + n
            if len(self._buf) < end:
                break
            kind, value = pickle.loads(self._buf[pos + _FRAME.size : end])
            pos, got = end, True
            if kind == _ITEM:  # its place in the spool file
                assert self._spool is not None  # (a generator's task)
                self._items.append(pickle.loads(_read_at(self._spool.fileno(), *value)))
            elif kind == _VALUE:
                self._items.append(value)
            else:  # the last message: the child is exiting, reaped later, not waited for here
                self._outcome = (kind == _RETURN, value)
                self._close()  # (drops the buffer too)
                _exiting.add(self.forked_pid)
                reap_exited()
                return True
        del self._buf[:pos]
        return got

    def _ended(self) -> None:
        """The pipe closed before the outcome came: the child died."""
        self._close()
        _, status = os.waitpid(self.forked_pid, 0)
        how = (
            f"killed by signal {os.WTERMSIG(status)}"
            if os.WIFSIGNALED(status)
            else f"exit status {os.waitstatus_to_exitcode(status)}"
        )
        self._outcome = (False, TaskDied(f"a helper process ended without a result ({how})"))

    def _close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
        if self._spool is not None:
            self._spool.close()
            self._spool = None
        self._buf = bytearray()

    def kill(self) -> None:
        if self._outcome is None and self.pid is not None:
            try:
                os.kill(self.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            while self._outcome is None:
                self._read(block=True)


def yield_from(gen: GeneratorType, put: Callable[[Any], None]) -> Any:
    """Run a generator to its end, ``put`` each value it yields; its return value."""
    while True:
        try:
            put(next(gen))
        except StopIteration as stop:
            return stop.value


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


def _run_child(fn: Callable[..., Any], args: tuple, w: int, spool) -> None:
    out = os.fdopen(w, "wb")
    try:
        value = fn(*args)
        if isinstance(value, GeneratorType):
            end = 0

            def put(item: Any) -> None:  # the value into the spool, its place through the pipe
                nonlocal end
                if spool is None:  # not a generator function (a wrapper): through the pipe, waiting
                    out.write(_frame(_VALUE, item))  # for the parent to read it
                    out.flush()
                    return
                data = _dumps(item)
                _write_at(spool.fileno(), data, end)
                out.write(_frame(_ITEM, (end, len(data))))
                out.flush()
                end += len(data)

            value = yield_from(value, put)
        kind: int = _RETURN
    except BaseException as exc:  # everything goes back to the parent, which raises it
        if not isinstance(exc, MemoryError):  # a note needs memory
            exc.add_note("in a forked helper process:\n" + traceback.format_exc())
        kind, value = _RAISE, exc
    try:
        frame = _frame(kind, value)
    except _Unpicklable as exc:  # an unpicklable value or exception: say what it was
        frame = _frame(_RAISE, TaskDied(f"a helper's result could not be sent back: {exc}"))
    out.write(frame)
    out.close()


class _Unpicklable(Exception):
    pass


def _dumps(value: Any) -> bytes:
    try:
        return pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
    except Exception as exc:
        raise _Unpicklable(repr(exc)) from None


def _frame(kind: int, value: Any) -> bytes:
    data = _dumps((kind, value))
    return _FRAME.pack(len(data)) + data


def _write_at(fd: int, data: bytes, offset: int) -> None:
    view = memoryview(data)
    while view:
        n = os.pwrite(fd, view, offset)
        view, offset = view[n:], offset + n


def _read_at(fd: int, offset: int, n: int) -> bytes:
    parts = []
    while n > 0:
        chunk = os.pread(fd, n, offset)
        if not chunk:
            raise TaskDied("a helper's value was cut short in its spool file")
        parts.append(chunk)
        offset, n = offset + len(chunk), n - len(chunk)
    return b"".join(parts)


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

    def free(self) -> int:
        """How many tasks could start now without waiting."""
        self._running = [t for t in self._running if not t.ready()]
        return self.limit - len(self._running)

    def wait_any(self) -> None:
        """Block until a running child sends something (a value or its outcome); at once if none runs
        or one has sent values no one has taken yet (``free`` reads what has come)."""
        running = [t for t in self._running if not t.done()]
        if not running or any(t._items for t in running):
            return
        ready, _, _ = select.select([t.fileno for t in running], [], [])
        for t in running:
            if t.fileno in ready:
                t._read(block=False)

    def _wait_one(self) -> None:
        """Block until one running child has sent its outcome (taking what the others send)."""
        while True:
            ready, _, _ = select.select([t.fileno for t in self._running], [], [])
            for t in list(self._running):
                if t.fileno in ready:
                    t._read(block=False)
                    if t.done():
                        self._running.remove(t)
                        return

    def __enter__(self) -> TaskGroup:
        return self

    def __exit__(self, *exc: object) -> None:
        for t in self._running:
            t.kill()  # no-op for those already collected by result()
        self._running.clear()
        reap_exited(block=True)
