"""coop_common.qos: ROS 2's QoS overrides on an `overridable` endpoint, as
`durable_overrides` writes them, and the shared profiles left as they were."""
import rclpy
from rclpy.context import Context
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
from sensor_msgs.msg import Image

from coop_common.qos import SENSOR_QOS, durable_overrides, overridable


def test_durable_overrides_make_an_overridable_subscription_reliable_and_transient_local():
    assert durable_overrides(['/rover1/stereo/pose'], 'publisher', depth=7)[:2] == \
        ['-p', 'qos_overrides./rover1/stereo/pose.publisher.reliability:=reliable']
    context = Context()
    rclpy.init(context=context, args=[])
    try:
        node = rclpy.create_node('qos_probe', namespace='rover1', context=context,
                                 cli_args=['--ros-args', *durable_overrides(
                                     ['/rover1/stereo/left/image_raw'], 'subscription',
                                     depth=7)])
        # relative names are resolved (namespace, remappings) before the override is looked up
        sub = node.create_subscription(Image, 'stereo/left/image_raw', lambda m: None,
                                       **overridable(SENSOR_QOS))
        other = node.create_subscription(Image, 'stereo/right/image_raw', lambda m: None,
                                         **overridable(SENSOR_QOS))
        q = sub.qos_profile
        assert (q.reliability, q.durability, q.depth) == (
            ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL, 7)
        # another topic and the shared profile are as they were
        assert other.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
        assert (SENSOR_QOS.reliability, SENSOR_QOS.depth) == (ReliabilityPolicy.BEST_EFFORT, 5)
        assert node.get_parameter(
            'qos_overrides./rover1/stereo/left/image_raw.subscription.depth').value == 7
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
