"""HandoffExecutor: rclpy's MultiThreadedExecutor, waiting for a worker to take each callback.

In rclpy 7.1.6 (the Jazzy wheels), while a callback handed to the thread pool has not started
yet, the executor's wait returns at once (ros2/rclpy#1452, fixed upstream after this release).
Its main thread then spins in Python, taking and dropping the GIL so often that the pool's
workers rarely got it: callbacks started 20-100 ms after their message was in (measured in the
node: DDS delivered a 3 MB cloud in 3 ms, its callback started p50 9 ms / p95 80 ms later).
Here the main thread blocks, without the GIL, until a worker has the callback in hand (or a
short timeout passes when all workers are busy), so it cannot starve them.
"""
from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

from rclpy.executors import (
    ConditionReachedException,
    ExternalShutdownException,
    MultiThreadedExecutor,
    ShutdownException,
    TimeoutException,
)

# Longest the main thread waits for a worker to start a callback. A free worker takes it in well
# under a millisecond; with all workers busy this turns the executor's spin into a slow poll.
HANDOFF_TIMEOUT_SEC = 0.005


class HandoffExecutor(MultiThreadedExecutor):
    """MultiThreadedExecutor whose spin waits until each submitted callback has started.

    It relies on the base class's pool and list of running handlers (private in rclpy); with an
    rclpy that has neither it behaves exactly as the base class.
    """

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._handoff = (isinstance(getattr(self, '_executor', None), ThreadPoolExecutor)
                         and isinstance(getattr(self, '_futures', None), list))

    def _spin_once_impl(self, timeout_sec: float | None = None,
                        wait_condition: Callable[[], bool] = lambda: False) -> None:
        if not self._handoff:
            super()._spin_once_impl(timeout_sec, wait_condition)
            return
        try:
            handler, _, _ = self.wait_for_ready_callbacks(timeout_sec, None, wait_condition)
        except (ExternalShutdownException, ShutdownException, TimeoutException,
                ConditionReachedException):
            return
        started = threading.Event()

        def run() -> None:
            started.set()
            handler()

        self._executor.submit(run)
        started.wait(HANDOFF_TIMEOUT_SEC)
        # as the base class: finished handlers are dropped, their exceptions raised here
        with getattr(self, '_futures_lock', None) or contextlib.nullcontext():
            self._futures.append(handler)
            done = [future for future in self._futures if future.done()]
            for future in done:
                self._futures.remove(future)
        for future in done:
            future.result()
