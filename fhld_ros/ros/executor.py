"""HandoffExecutor: rclpy's MultiThreadedExecutor, waiting for a worker to take each callback.

In rclpy 7.1.6 (the Jazzy wheels), while a callback handed to the thread pool has not started
yet, the executor's wait returns at once (ros2/rclpy#1452, fixed upstream after this release).
Its main thread then spins in Python, taking and dropping the GIL so often that the pool's
workers rarely got it: callbacks started 20-100 ms after their message was in (measured in the
node: DDS delivered a 3 MB cloud in 3 ms, its callback started p50 9 ms / p95 80 ms later).
Here the main thread blocks, without the GIL, until a worker has the callback in hand (or a
short timeout passes when all workers are busy), so it cannot starve them.

spin() runs a node on it; run_node() is both nodes' main() around that (rclpy.init, the node
built with signals held, one-line errors, clean shutdown). Nothing here imports a model, so the
camera node starts without the LiDAR node's.
"""
from __future__ import annotations

import contextlib
import gc
import sys
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import rclpy
from rclpy.executors import (
    ConditionReachedException,
    ExternalShutdownException,
    MultiThreadedExecutor,
    ShutdownException,
    TimeoutException,
)
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node

from fhld_ros.errors import ConfigError
from fhld_ros.ros import stop
from fhld_ros.ros.declare import rcl_reason

# Longest the main thread waits for a worker to start a callback. A free worker takes it in well
# under a millisecond; with all workers busy this turns the executor's spin into a slow poll.
HANDOFF_TIMEOUT_SEC = 0.005
GIL_SWITCH_SEC = 0.0005  # see run_node()


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


def spin(node: Node) -> None:
    """Spin `node` until Ctrl-C or shutdown, then stop the executor's workers before returning."""
    # A MultiThreadedExecutor that cannot starve its workers (see the module doc)
    executor = HandoffExecutor(num_threads=3, context=node.context)
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except rclpy_implementation.RCLError:
        if node.context.ok():
            raise
        # a signal shut the context down while the executor was building its wait set
    finally:
        executor.shutdown()
        # Jazzy's Executor.shutdown() does not wait for callbacks still running in the pool;
        # destroying the node under one crashed the process (SIGSEGV, ~1 in 8 stops on a busy
        # machine). Join the pool first.
        pool = getattr(executor, '_executor', None)
        if pool is not None:
            pool.shutdown(wait=True)


def run_node(name: str, make_node: Callable[[], Node], args: Sequence[str] | None) -> int:
    """A node's main(): run `make_node()` until a signal; 0 when stopped, 2 with one line
    `<name>: error: ...` for bad ROS arguments, parameters or weights.

    A SIGINT or SIGTERM at any moment exits 0 without a traceback: rclpy shuts the context down,
    and whatever rclpy call comes next fails; that failure is the stop, not an error. (Before
    rclpy.init, fhld_ros/ros/lane_detector.py takes care of the signals.)
    """
    try:
        rclpy.init(args=args)
    except rclpy_implementation.RCLError as exc:  # arguments rcl cannot parse ('-p name:=')
        reason = rcl_reason(exc).removeprefix('failed to initialize rcl: ')
        print(f'{name}: error: bad ROS arguments: {reason}', file=sys.stderr)
        return 2
    try:
        with stop.held():  # signals are recorded while it is built: see ros/stop.py
            node = make_node()
    except (KeyboardInterrupt, ExternalShutdownException):
        rclpy.try_shutdown()
        return 0
    except ConfigError as exc:
        if not rclpy.ok():
            return 0  # stopped by a signal while the node was being built
        # bad parameters or checkpoint: one line naming the problem, no traceback
        print(f'{name}: error: {exc}', file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    except Exception:
        # A signal while the node is being built makes whatever runs then fail (an rclpy call
        # on the shut-down context, an extension's import interrupted mid-way): that is the stop.
        if rclpy.ok():
            raise
        return 0
    if stop.received:  # a held stop: the node was built, but nothing is to run
        node.destroy_node()
        rclpy.try_shutdown()
        return 0
    # The executor's Python wait loop and the detection thread share the GIL; the model gives it
    # up in every torch op and, at the default 5 ms switch interval, waited that long to get it
    # back each time (measured: detections 2x slower in the node than alone).
    sys.setswitchinterval(GIL_SWITCH_SEC)
    # A full garbage collection walks every object torch and rclpy created at start-up (~200k,
    # ~95 ms here) holding the GIL, and stalled callbacks at random (measured: cloud callbacks
    # up to 60-100 ms late). Frozen objects are left out of collections.
    gc.freeze()
    try:
        spin(node)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
