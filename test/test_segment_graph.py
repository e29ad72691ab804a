"""Two rovers carry one segment into a truss stage over DDS (app. A.4, issue #36): the installed
`rover_sim sim` in its segment scenario, `coop_insertion segment_master` and `segment_slave` as
separate processes that share nothing but the master's reference topic; an `insert_segment`
goal from this process. The simulator's truth judges: seated, the internal force between the
rovers under its limit, the slave's estimate of the master's force against the master's true
grasp force. Then the master falls silent and the slave must hold and let the part settle."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.graph


@pytest.fixture
def probe():
    from coop_common.testing import Probe
    p = Probe('segment_probe')
    yield p
    p.close()

#: the internal force the task must stay under (N), the experiment's default limit
INTERNAL_LIMIT_N = 20.0


#: the segment scenario's world: a real arm's encoders (the config file says why)
WORLD = Path(__file__).resolve().parents[1] / 'src/rover_sim/config/segment_world.yaml'


def _sim_args(*extra: str) -> list[str]:
    return ['-p', 'scenario:=segment', '-p', f'world_yaml:={WORLD}', '-p', 'render_workers:=0',
            *extra]


def _sim_s(msg) -> float:
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


def _norm(v) -> float:
    return math.sqrt(v.x * v.x + v.y * v.y + v.z * v.z)


def test_two_rovers_seat_the_segment_over_dds(tmp_path, probe):
    """In lockstep (the outcome does not depend on load): the master's goal succeeds, the truth
    has the segment seated, the internal force never passed the limit, and in free carriage
    the slave's surrogate estimate of the master's force is within 0.5 N of the truth."""
    from rclpy.action import ActionClient

    from coop_common.testing import NodeProcess
    from coop_msgs.action import InsertSegment
    from coop_msgs.msg import PartEstimate, SegmentTruth
    probe.listen(SegmentTruth, '/sim/segment')
    probe.listen(PartEstimate, '/rover2/segment/estimate')
    sim = NodeProcess('rover_sim', 'sim', _sim_args(
        '-p', 'lockstep_participants:=[segment_master, segment_slave]',
        '-p', 'real_time_factor:=0.0'), log_path=tmp_path / 'sim.log')
    master = NodeProcess('coop_insertion', 'segment_master',
                         ['-p', 'lockstep:=true', '-p', 'use_sim_time:=true'],
                         log_path=tmp_path / 'master.log')
    slave = NodeProcess('coop_insertion', 'segment_slave',
                        ['-p', 'lockstep:=true', '-p', 'use_sim_time:=true'],
                        log_path=tmp_path / 'slave.log')
    with sim, master, slave:
        procs = (sim, master, slave)
        client = ActionClient(probe.node, InsertSegment, '/rover1/insert_segment')
        probe.spin_until(client.server_is_ready, 60.0, 'the insert_segment action', procs)
        # a goal sent before the server has matched our response reader can lose its answer
        # (see test_bag_replay): rejected goals (an infinite belief) until one is answered
        for _ in range(10):
            ping = client.send_goal_async(InsertSegment.Goal(stage_x=math.inf))
            try:
                probe.spin_until(ping.done, 3.0, "a rejected goal's answer", procs)
                break
            except TimeoutError:
                continue
        assert ping.done() and not ping.result().accepted
        # the master's belief of the channel: where the scenario puts it as the master sees it
        # (its nominal arm mount is 1 cm from the truth), to 0.5 mm. The search from a belief
        # off by more is the unit tests' and appendix_a's (docs/results/appendix-a.md: over
        # DDS as in-process, a search that starts with wall contacts can run out of time)
        fut = client.send_goal_async(InsertSegment.Goal(stage_x=-1.570, stage_top_z=math.nan,
                                                        timeout_s=60.0))
        probe.spin_until(fut.done, 10.0, 'the goal response', procs)
        handle = fut.result()
        assert handle.accepted
        res = handle.get_result_async()
        probe.spin_until(res.done, 600.0, 'the insertion', procs)
        probe.spin_for(0.5)
    result = res.result().result
    truths = probe.msgs['/sim/segment']
    print(f'{result.reason}: {result.tries} tries, {result.duration_s:.1f} sim s; '
          f'{len(truths)} truths')
    assert result.success, result.reason + '\n' + master.log_text()[-3000:]
    assert truths and truths[-1].seated
    peak = max(t.internal_force_n for t in truths)
    assert peak <= INTERNAL_LIMIT_N, peak
    assert max(t.max_penetration_m for t in truths) <= 1e-3
    # the estimate against the truth at the same stamps, while nothing touches the part
    true_at = {(t.header.stamp.sec, t.header.stamp.nanosec): t for t in truths}
    errs = [e.partner_force for e in probe.msgs['/rover2/segment/estimate']]
    pairs = []
    for e in probe.msgs['/rover2/segment/estimate']:
        t = true_at.get((e.header.stamp.sec, e.header.stamp.nanosec))
        if t is not None and _norm(t.contact_force) < 0.05 and not e.partner_silent:
            f = t.grasp_force[0]
            p = e.partner_force
            pairs.append((p.x - f.x, p.y - f.y, p.z - f.z))
    assert errs and len(pairs) >= 50, len(pairs)
    rms = float(np.sqrt(np.mean(np.sum(np.square(pairs), axis=1))))
    print(f'partner-force estimate: rms {rms:.3f} N over {len(pairs)} free samples')
    assert rms < 0.5


def test_a_silent_master_leaves_the_slave_holding(tmp_path, probe):
    """Live pacing: the two hold the segment, then the master's process is stopped. The slave
    says its partner is silent and holds: the part stays where it was (its grasp does not
    follow a plan that is not coming) and the internal force stays small."""
    from coop_common.testing import NodeProcess
    from coop_msgs.msg import PartEstimate, SegmentTruth
    probe.listen(SegmentTruth, '/sim/segment')
    probe.listen(PartEstimate, '/rover2/segment/estimate')
    sim = NodeProcess('rover_sim', 'sim', _sim_args(), log_path=tmp_path / 'sim.log')
    master = NodeProcess('coop_insertion', 'segment_master', ['-p', 'use_sim_time:=true'],
                         log_path=tmp_path / 'master.log')
    slave = NodeProcess('coop_insertion', 'segment_slave', ['-p', 'use_sim_time:=true'],
                        log_path=tmp_path / 'slave.log')
    est = probe.msgs['/rover2/segment/estimate']
    truths = probe.msgs['/sim/segment']
    with sim, master, slave:
        probe.spin_until(lambda: len(est) > 100 and not est[-1].partner_silent and truths,
                         120.0, "the slave hearing the master's reference, the probe the truth",
                         (sim, master, slave))
        master.stop()
        probe.spin_until(lambda: est[-1].partner_silent, 30.0, 'the slave saying silent',
                         (sim, slave))
        start = len(truths)
        z0 = truths[-1].pose.position.z
        t0 = _sim_s(truths[-1])
        # 3 s of sim time, however slowly a loaded machine lets it pass
        probe.spin_until(lambda: _sim_s(truths[-1]) >= t0 + 3.0, 60.0, '3 s of holding',
                         (sim, slave))
    held = truths[start:]
    assert len(held) > 20
    assert 'silent: holding' in slave.log_text()
    # the master's arm, its process gone, keeps its last set-point but loses the torques that
    # held its share of the part (the simulator drops stale ones): its side sinks up to 2 cm
    # (measured under load); a slave that followed a plan or pushed on would move it more
    assert max(abs(t.pose.position.z - z0) for t in held) < 0.03
    # the master's side sinking loads the part; the slave yields to it (never pushes on): the
    # internal force stays under the task's limit and falls from its peak
    peak = max(t.internal_force_n for t in held)
    assert peak < INTERNAL_LIMIT_N
    assert held[-1].internal_force_n <= max(2.0, 0.5 * peak), [
        round(t.internal_force_n, 2) for t in held[::10]]
