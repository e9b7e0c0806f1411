"""Chunks of one thread's work that another thread may help with (the pipeline's two threads).

The thread that owns some chunked work calls `WorkShare.run(fn, items)`: fn(item) runs once for
every item, on the owner or on a helper, and `run` returns when all are done. Another thread that
finds itself idle calls `WorkShare.help()`: it takes items of whatever work is being run until none
is left. Items must write disjoint outputs; their order does not matter.

Why: after the mesh, the SDF volume of a map whose voxel centres are not nodes of its
closest-point grid (an anisotropic map) queries its 12M voxel centres in chunks on its own thread,
the last work of the run, while the main thread, done with the skeleton and the files, waited.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable


class _Job:
    """One `WorkShare.run`: its items, the next one to take, how many are running, the first error."""

    def __init__(self, fn: Callable, items: list):
        self.fn, self.items = fn, items
        self.next, self.running, self.error = 0, 0, None
        self.cond = threading.Condition()

    def _none_left(self) -> bool:
        """No item left to take: all taken, or an item failed (call under self.cond)."""
        return self.next >= len(self.items) or self.error is not None

    def _take(self) -> int | None:
        with self.cond:
            if self._none_left():
                return None
            self.next += 1
            self.running += 1
            return self.next - 1

    def work(self) -> None:
        """Run items until none is left to take (an item's error stops the taking, and is kept)."""
        while (i := self._take()) is not None:
            try:
                self.fn(self.items[i])
            except BaseException as e:  # noqa: BLE001 - the owner re-raises it
                with self.cond:
                    self.error = self.error or e
            finally:
                with self.cond:
                    self.running -= 1
                    self.cond.notify_all()

    def wait(self) -> None:
        """Until no item is running and none is left to take."""
        with self.cond:
            self.cond.wait_for(lambda: self.running == 0 and self._none_left())


class WorkShare:
    """Work in chunks that one thread runs (`run`) and other threads may help with (`help`)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._job: _Job | None = None

    def run(self, fn: Callable, items: Iterable) -> None:
        """fn(item) for every item, here or on a helping thread; returns when all are done. Raises the
        first error an item raised (the items not yet taken are then not run)."""
        job = _Job(fn, list(items))
        with self._lock:
            self._job = job
        try:
            job.work()
            job.wait()
        finally:
            with self._lock:
                self._job = None
        if job.error is not None:
            raise job.error

    def help(self) -> bool:
        """Run items of the work being run, if any, until none is left to take; whether there was
        work to help with. An item's error goes to the thread that runs the work, not here."""
        with self._lock:
            job = self._job
        if job is None:
            return False
        job.work()
        return True
