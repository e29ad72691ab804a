"""QoS profiles of the graph (house style: sensor streams, latched state, commands)."""
from __future__ import annotations

import copy
from collections.abc import Iterable
from typing import Any, Literal

from rclpy.qos import (
                       DurabilityPolicy,
                       HistoryPolicy,
                       QoSProfile,
                       ReliabilityPolicy,
                       qos_profile_sensor_data,
)
from rclpy.qos_overriding_options import QoSOverridingOptions, QoSPolicyKind

#: Sensor streams: best effort, keep last 5 (publishers and subscribers alike).
SENSOR_QOS: QoSProfile = qos_profile_sensor_data
#: Maps, estimates and other state a late joiner must get: reliable, transient local, depth 1.
LATCHED_QOS = QoSProfile(
    depth=1, history=HistoryPolicy.KEEP_LAST,
    reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
#: Commands: reliable, volatile, a short queue.
COMMAND_QOS = QoSProfile(
    depth=10, history=HistoryPolicy.KEEP_LAST,
    reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE,
)
#: /clock: as rosgraph (best effort would drop ticks under load; the sim publishes reliably).
CLOCK_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)


def with_depth(q: QoSProfile, depth: int) -> QoSProfile:
    """`q` with another queue depth (a subscriber's buffer; matching is unaffected)."""
    return QoSProfile(history=q.history, depth=depth, reliability=q.reliability,
                      durability=q.durability)


def reliable(qos: QoSProfile, depth: int = 100) -> QoSProfile:
    """`qos` made reliable with a deeper queue: a lockstep stream may not drop a message (a
    reliable writer still serves best-effort readers)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=max(depth, qos.depth),
                      reliability=ReliabilityPolicy.RELIABLE, durability=qos.durability)


#: Map contributions (coop_msgs/MapContribution): reliable and transient local with a deep
#: history, so what a rover makes while its link is down reaches the mapper when the link
#: returns, also to a mapper that restarts or joins late (its ledger skips what it has fused).
#: 400 at the stereo's 4 Hz is 100 s of contributions; `contribution_history` sets it.
CONTRIBUTION_QOS = QoSProfile(
    depth=400, history=HistoryPolicy.KEEP_LAST,
    reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL,
)


#: what `overridable` lets a user change: rclpy's default policies and durability
OVERRIDABLE_POLICIES = [QoSPolicyKind.HISTORY, QoSPolicyKind.DEPTH, QoSPolicyKind.RELIABILITY,
                        QoSPolicyKind.DURABILITY]


def overridable(qos: QoSProfile) -> dict[str, Any]:
    """Keyword arguments of `create_subscription` / `create_publisher` with which ROS 2's QoS
    overrides (read-only parameters `qos_overrides.<topic>.<publisher|subscription>.<policy>`,
    set at start) may change `qos`. A copy: rclpy writes the overrides into the profile it is
    given, and the profiles here are shared."""
    return {'qos_profile': copy.copy(qos),
            'qos_overriding_options': QoSOverridingOptions(OVERRIDABLE_POLICIES)}


def durable_overrides(topics: Iterable[str], endpoint: Literal['publisher', 'subscription'],
                      *, depth: int = 100) -> list[str]:
    """`--ros-args` QoS overrides that make `topics` (resolved names) reliable and transient
    local with history `depth`, for a replay that must deliver every message: a subscriber
    that matches late (discovery is not symmetric: a writer may see its reader before the
    reader sees it) still gets the last `depth` messages, and one that falls behind loses
    none of them. Both ends need them: the player's publishers and the consumer's
    subscriptions (a transient-local reader does not match a volatile writer)."""
    policies = {'reliability': 'reliable', 'durability': 'transient_local',
                'history': 'keep_last', 'depth': str(depth)}
    return [a for t in topics for k, v in policies.items()
            for a in ('-p', f'qos_overrides.{t}.{endpoint}.{k}:={v}')]
