"""The transform tree on `/tf` and `/tf_static` (tf2_msgs/TFMessage), published the way tf2_ros's
broadcasters do (the same topics and QoS: any tf2 listener, RViz or Foxglove reads it), from
`coop_common.frames`' transforms. tf2 itself is not needed: the tree is messages.

Optional where the message is missing: without `tf2_msgs` (the pinned venv alone) a
`TreeBroadcaster` logs once that the tree is off and publishes nothing; the node runs as before.
"""
from __future__ import annotations

import time
from collections.abc import Iterable

from builtin_interfaces.msg import Time
from geometry_msgs.msg import TransformStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from .frames import Transform

__all__ = ['TF_QOS', 'TF_STATIC_LISTENER_QOS', 'TF_STATIC_QOS', 'TreeBroadcaster']

#: tf2_ros's DynamicBroadcasterQoS (and listener's)
TF_QOS = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                    reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE)
#: tf2_ros's StaticBroadcasterQoS: each publisher's latest set, to every late joiner
TF_STATIC_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                           reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: tf2_ros's StaticListenerQoS: deep, as every static publisher's set may arrive at once
TF_STATIC_LISTENER_QOS = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                                    reliability=ReliabilityPolicy.RELIABLE,
                                    durability=DurabilityPolicy.TRANSIENT_LOCAL)

def _stamped(t: Transform, stamp: Time) -> TransformStamped:
    m = TransformStamped()
    m.header.stamp, m.header.frame_id, m.child_frame_id = stamp, t.parent, t.child
    tr, q = m.transform.translation, m.transform.rotation
    tr.x, tr.y, tr.z = t.translation
    q.x, q.y, q.z, q.w = t.rotation
    return m


class TreeBroadcaster:
    """`node`'s part of the tree: `send_static` (latched on /tf_static: every static transform
    this node ever sent, in one message, as tf2_ros's StaticTransformBroadcaster) and `send`
    (/tf). `enabled` is False when asked off or tf2_msgs is missing (logged once).

    `owned`: the child frames this node publishes the transforms of; with `check_s` > 0 the
    constructor listens that long to /tf_static first and raises ValueError when another node
    already publishes one of them (a frame prefix that collides with another team's)."""

    def __init__(self, node: Node, *, enabled: bool = True, owned: Iterable[str] = (),
                 check_s: float = 0.0) -> None:
        self._node = node
        self._static: dict[str, TransformStamped] = {}
        self.enabled = False
        if not enabled:
            return
        try:
            from tf2_msgs.msg import TFMessage  # noqa: PLC0415 - an optional dependency
        except ImportError:
            node.get_logger().info('tf2_msgs is not installed: no transform tree (/tf, '
                                   '/tf_static) from this node')
            return
        self._msg = TFMessage
        if check_s > 0:
            self._refuse_taken(set(owned), check_s)
        self._tf = node.create_publisher(TFMessage, '/tf', TF_QOS)
        self._tf_static = None         # made by the first send_static: not every node has any
        self.enabled = True

    def _refuse_taken(self, ours: set[str], check_s: float) -> None:
        taken: set[str] = set()

        def on_static(msg) -> None:
            taken.update(t.child_frame_id for t in msg.transforms)

        # a node of its own: the real one is not yet in its executor, and must not have been
        # in another one (a lifecycle node's services stopped answering after that)
        node = self._node
        # (no global arguments: a use_sim_time or a /clock remap for the process would give it
        # a clock subscription that outlives it in the graph's discovery caches)
        probe = Node(f'{node.get_name()}_frame_check', namespace=node.get_namespace(),
                     context=node.context, start_parameter_services=False,
                     enable_rosout=False, use_global_arguments=False)
        probe.create_subscription(self._msg, '/tf_static', on_static, TF_STATIC_LISTENER_QOS)
        executor = SingleThreadedExecutor(context=node.context)
        try:
            executor.add_node(probe)
            end = time.monotonic() + check_s
            # a bounded wait: discovery has no "everyone is here" event to wait for
            while time.monotonic() < end and not taken & ours:
                executor.spin_once(timeout_sec=max(0.0, min(0.05, end - time.monotonic())))
        finally:
            executor.shutdown()
            probe.destroy_node()
        clash = sorted(taken & ours)
        if clash:
            raise ValueError(f'another node already publishes frame(s) {", ".join(clash[:4])} '
                             'on /tf_static: give this team its own frame_prefix')

    @property
    def listened(self) -> bool:
        """Someone subscribes to /tf (else `send` may be skipped: nothing is built)."""
        return self.enabled and self._tf.get_subscription_count() > 0

    def send_static(self, transforms: Iterable[Transform], stamp: Time) -> None:
        if not self.enabled:
            return
        for t in transforms:
            self._static[t.child] = _stamped(t, stamp)
        if self._tf_static is None:
            self._tf_static = self._node.create_publisher(self._msg, '/tf_static',
                                                          TF_STATIC_QOS)
        self._tf_static.publish(self._msg(transforms=list(self._static.values())))

    def send(self, transforms: Iterable[Transform], stamp: Time) -> None:
        if not self.enabled:
            return
        msgs = [_stamped(t, stamp) for t in transforms]
        if msgs:
            self._tf.publish(self._msg(transforms=msgs))
