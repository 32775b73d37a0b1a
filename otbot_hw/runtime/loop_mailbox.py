"""Work handed to the control loop's thread from other threads (the control socket's dispatch thread)."""
from __future__ import annotations

import queue
from concurrent.futures import Future
from typing import Any, Callable


class LoopMailbox:
    """Work for the loop thread: other threads ``call(fn)`` (blocking, with a timeout) or
    ``submit(fn)`` (a Future); the loop calls ``service()`` once per cycle, which runs what is
    queued on the loop thread without ever waiting. A call the loop has not picked up within
    the timeout raises ``TimeoutError`` and is dropped (it never runs late)."""

    def __init__(self, max_per_cycle: int = 4):
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self.max_per_cycle = max_per_cycle

    def submit(self, fn: Callable[[], Any]) -> Future:
        fut: Future = Future()
        self._queue.put((fn, fut))
        return fut

    def call(self, fn: Callable[[], Any], timeout: float = 1.0) -> Any:
        fut = self.submit(fn)
        try:
            return fut.result(timeout)
        except TimeoutError:
            if fut.cancel():
                raise TimeoutError(f"the control loop did not take the command within {timeout:g} s") from None
            return fut.result()  # picked up just now: wait for it

    def service(self) -> int:
        """Run up to ``max_per_cycle`` queued calls on the calling (loop) thread; returns how many."""
        n = 0
        while n < self.max_per_cycle:
            try:
                fn, fut = self._queue.get_nowait()
            except queue.Empty:
                break
            if not fut.set_running_or_notify_cancel():
                continue
            n += 1
            try:
                fut.set_result(fn())
            except BaseException as exc:  # handed back to the caller's thread
                fut.set_exception(exc)
        return n

