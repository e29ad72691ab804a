"""QoS profiles of the graph (house style: sensor streams, latched state, commands)."""
from __future__ import annotations

from rclpy.qos import (
                       DurabilityPolicy,
                       HistoryPolicy,
                       QoSProfile,
                       ReliabilityPolicy,
                       qos_profile_sensor_data,
)

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
