"""Lockstep (issue #32): the simulator steps no round before the master, the slave and the
rig have answered the last, so an attempt's outcome does not depend on how busy the machine
is, nor on how its nodes share processes. The same short insertion twice through the
installed nodes, the second beside a process that keeps a core busy and with the master and the
slave composed in one process (`coop_bringup compose`): the same result to the last digit of
its peak force."""
from __future__ import annotations

import math
import os

import pytest

pytestmark = pytest.mark.graph

#: rounds of 20 ms (the rig's default: 10 ms): the check holds for any round, in half the rounds
ROUND_S = 0.02
#: the master's camera given in front of the site, 0.5 m from the task's target (the site's
#: mouth 0.15 m out and 0.1 m up), looking back at it
CAMERA = ((3.0572, 0.65), -math.pi / 2, math.atan2(0.8 - 0.5, 0.5))


def short_attempt(log_dir, *, composed=False):
    from coop_bringup.rig import InsertionRig

    from coop_common.rover_geometry import camera_mount
    # the master starts where its given camera pose puts it, the slave's card 0.05 m short of
    # the slot, descending at 3 cm/s: a short attempt
    mount = camera_mount(*CAMERA)
    with InsertionRig(seed=1, slot_in=5.0, occlusion_density=0.0, planner=False,
                      overrides={'master': {'slot_wait_s': 0.5},
                                 'slave': {'descent_speed_m_s': 0.03}},
                      log_dir=log_dir, lockstep=True, round_s=ROUND_S,
                      master_start=(*mount.base_xy, mount.base_yaw), slave_start_short_m=0.05,
                      composed=composed, domain_id=int(os.environ['ROS_DOMAIN_ID'])) as rig:
        return rig.attempt(slot_in=5.0, placement='given', camera=CAMERA, seed=3,
                           timeout_s=40.0)


def test_lockstep_gives_the_same_attempt_beside_a_busy_core_and_composed(tmp_path):
    from coop_common.testing import busy_core
    idle = short_attempt(tmp_path / 'idle')
    with busy_core():
        busy = short_attempt(tmp_path / 'busy', composed=True)
    print(f'idle: {idle.duration_s:.0f} s wall, busy: {busy.duration_s:.0f} s wall')
    assert idle.success, idle.reason            # a check that can fail: the attempt seats
    for a in (idle, busy):
        a.curves.clear()       # the feedback is sampled by wall time; the outcome is not
        a.duration_s = 0.0
    assert busy == idle


def test_a_participant_that_never_answers_holds_the_sim_and_is_named(tmp_path):
    from coop_common.testing import NodeProcess, wait_for
    args = ['-p', 'lockstep_participants:=[ghost]', '-p', 'lockstep_timeout_s:=1.0',
            '-p', 'stereo_rate_hz:=0.0']
    with NodeProcess('rover_sim', 'sim', args, log_path=tmp_path / 'sim.log') as sim:
        # the simulator stays at round 0 (it never runs ahead) and says whom it waits for
        wait_for(lambda: sim.log_text().count('no answer to round 0 from /ghost') >= 2, 60,
                 what="the simulator's second word on /ghost")
        assert sim.alive()
