"""The master node in-process (a private Context and domain), its callbacks fed directly."""
from __future__ import annotations

import math

import pytest
import rclpy
from nav_msgs.msg import Odometry
from rclpy.context import Context
from sensor_msgs.msg import Image

from coop_common.testing import pick_domain_id
from coop_insertion.master_node import MasterNode


@pytest.fixture
def master():
    ctx = Context()
    rclpy.init(context=ctx, domain_id=pick_domain_id() + 110)
    node = MasterNode(context=ctx)
    yield node
    node.destroy_node()
    rclpy.shutdown(context=ctx)


def _at(msg, t: float):
    msg.header.stamp.sec = int(t)
    msg.header.stamp.nanosec = round((t - int(t)) * 1e9)
    return msg


def _pair(node: MasterNode, t: float) -> None:
    for side in ('left', 'right'):
        node._on_image(side, _at(Image(width=4, height=4, encoding='mono8', step=4,
                                       data=bytes(16)), t))


def test_stamps_kept_from_before_a_sim_reset_do_not_outlive_it(master):
    """A simulator reset between two goals starts the sensors' time again from 0. The stamps
    the master keeps (the last frame's, the last arrival's) must start again with it: else the
    last frame of the goal before stands ahead of every new frame, and each look for the slot
    in the next goal ends before it began (the table's later attempts searched blind until the
    clock passed the one before's end)."""
    master._on_odom(_at(Odometry(), 150.0))
    _pair(master, 150.0)
    master._arrived_t = 149.0          # the goal before ended standing at its camera pose
    assert master._image_t == 150.0
    # the reset: odometry from 0.02 s, then a frame at 0.5 s
    master._on_odom(_at(Odometry(), 0.02))
    assert master._image_t == -math.inf and master._arrived_t == -math.inf
    _pair(master, 0.5)
    assert master._image_t == 0.5
    # and a late frame or odometry message is not a jump back
    _pair(master, 0.25)
    master._on_odom(_at(Odometry(), 0.01))
    assert master._image_t == 0.5
