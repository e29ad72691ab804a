"""The recorder's and player's shared main loop: SIGINT/SIGTERM only set a flag, so a write or
publish in flight always completes before the node shuts down in order."""
from __future__ import annotations

import signal
import threading
from collections.abc import Callable
from typing import Any

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from .bagio import BagError


def spin_until_stopped(factory: Callable[[], Node], argv: list[str], *, logger: str,
                       done: Callable[[Node], bool] = lambda node: False,
                       before_destroy: Callable[[Node], None] = lambda node: None,
                       executor_factory: Callable[[], Any] = SingleThreadedExecutor) -> int:
    """Init rclpy with `argv`, build the node, spin until a signal, `done(node)` or an external
    shutdown; a node that cannot start logs why and returns 1."""
    stop = threading.Event()
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    previous = {sig: signal.signal(sig, lambda *_: stop.set())
                for sig in (signal.SIGINT, signal.SIGTERM)}
    node = None
    try:
        try:
            node = factory()
        except (ValueError, OSError, BagError, ParameterException) as exc:
            rclpy.logging.get_logger(logger).fatal(str(exc))
            return 1
        executor = executor_factory()
        executor.add_node(node)
        while rclpy.ok() and not stop.is_set() and not done(node):
            executor.spin_once(timeout_sec=0.1)
    except ExternalShutdownException:
        pass
    finally:
        if node is not None:
            before_destroy(node)
            node.destroy_node()
        rclpy.try_shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
