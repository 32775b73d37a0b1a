"""Where many independent fits run: in this process, in local worker processes, or on Dask.

``make_executor(scheduler=None, workers=None)`` returns an ``Executor`` with
``map(fn, items, progress=None) -> list`` (results in the order of ``items``):

* ``SerialExecutor``: in this process (workers=1, and for debugging);
* ``LocalExecutor``: ``concurrent.futures.ProcessPoolExecutor`` (default: one worker per CPU);
* ``DaskExecutor``: a Dask distributed cluster at ``scheduler`` (``tcp://host:8786``), or an
  existing ``distributed.Client``; the work is spread over every worker of the cluster.

``fn`` must be a module-level function (it is pickled to the workers) and each item
self-contained. ``progress(done, total)`` is called as results come in. Use as a context
manager or call ``close()``; executors are reusable for many ``map`` calls.

Interrupts: local workers ignore SIGINT, so Ctrl-C (to the whole process group) or a SIGINT to
the parent alone reaches only the parent. ``map`` then ends the work it started (local workers
are terminated and the executor closed, Dask futures cancelled) before the ``KeyboardInterrupt``
goes on; leaving the ``with`` block on any exception does the same instead of waiting for
running items.
"""
from __future__ import annotations

import os
import signal
from typing import Any, Callable, Iterable

from otbot_hw.extras import require

Progress = Callable[[int, int], None] | None


class Executor:
    """Common interface; subclasses implement ``map``."""

    kind = "abstract"

    def map(self, fn: Callable, items: Iterable, progress: Progress = None) -> list:  # pragma: no cover
        raise NotImplementedError

    def describe(self) -> str:
        return self.kind

    def close(self) -> None:
        pass

    def abort(self) -> None:
        """End all work now (nothing waits for running items); default: ``close``."""
        self.close()

    def __enter__(self) -> "Executor":
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


class SerialExecutor(Executor):
    """Runs every item in this process, one after the other."""

    kind = "serial"

    def map(self, fn, items, progress: Progress = None) -> list:
        items = list(items)
        out = []
        for i, it in enumerate(items):
            out.append(fn(it))
            if progress:
                progress(i + 1, len(items))
        return out


def _ignore_sigint() -> None:
    """Worker initializer: interrupts are the parent's to handle (it terminates the workers)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


class LocalExecutor(Executor):
    """A pool of local worker processes (``ProcessPoolExecutor``)."""

    kind = "local processes"

    def __init__(self, workers: int | None = None):
        from concurrent.futures import ProcessPoolExecutor

        self.workers = workers or os.cpu_count() or 1
        self._pool = ProcessPoolExecutor(max_workers=self.workers, initializer=_ignore_sigint)

    def describe(self) -> str:
        return f"{self.kind} ({self.workers} workers)"

    def map(self, fn, items, progress: Progress = None) -> list:
        from concurrent.futures import as_completed

        items = list(items)
        try:
            futs = {self._pool.submit(fn, it): i for i, it in enumerate(items)}
            out: list[Any] = [None] * len(items)
            for done, fut in enumerate(as_completed(futs), start=1):
                out[futs[fut]] = fut.result()
                if progress:
                    progress(done, len(items))
        except BaseException:
            self.abort()
            raise
        return out

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

    def abort(self) -> None:
        """Cancel queued items and terminate the workers (SIGTERM, then SIGKILL after 1 s)."""
        terminate = getattr(self._pool, "terminate_workers", None)  # Python >= 3.14
        if terminate is not None:
            terminate()
            return
        procs = list((getattr(self._pool, "_processes", None) or {}).values())  # no public handle before 3.14
        self._pool.shutdown(wait=False, cancel_futures=True)
        for proc in procs:
            if proc.is_alive():
                proc.terminate()
        for proc in procs:
            proc.join(timeout=1.0)
            if proc.is_alive():
                proc.kill()
                proc.join(timeout=1.0)


class DaskExecutor(Executor):
    """Work on a Dask distributed cluster (``distributed.Client``)."""

    kind = "dask"

    def __init__(self, scheduler: str | None = None, client=None, timeout: float = 10.0):
        Client = require("distributed").Client

        if client is None and not scheduler:
            raise ValueError("DaskExecutor needs a scheduler address or a client")
        self._own = client is None
        try:
            self.client = client or Client(scheduler, timeout=timeout)
        except OSError as exc:
            raise ConnectionError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
        self.scheduler = scheduler or self.client.scheduler.address

    def describe(self) -> str:
        n = len(self.client.scheduler_info().get("workers", {}))
        return f"{self.kind} ({self.scheduler}, {n} workers)"

    def map(self, fn, items, progress: Progress = None) -> list:
        as_completed = require("distributed").as_completed

        items = list(items)
        futs = self.client.map(fn, items, pure=False)
        try:
            index = {f.key: i for i, f in enumerate(futs)}
            out: list[Any] = [None] * len(items)
            for done, fut in enumerate(as_completed(futs), start=1):
                out[index[fut.key]] = fut.result()
                if progress:
                    progress(done, len(items))
        except BaseException:
            self.client.cancel(futs)
            raise
        return out

    def close(self) -> None:
        if self._own:
            self.client.close()


def make_executor(scheduler: str | None = None, workers: int | None = None) -> Executor:
    """Dask when ``scheduler`` is given, else local processes (serial for ``workers`` == 1)."""
    if scheduler:
        return DaskExecutor(scheduler)
    if workers == 1:
        return SerialExecutor()
    return LocalExecutor(workers)
