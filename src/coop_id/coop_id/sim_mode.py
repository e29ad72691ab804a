"""`table_2_1 --sim`: one identification end to end through the rover_sim and identifier nodes.

Starts the installed `rover_sim sim` (one rover, no stereo rendering) and `coop_id identifier`
under /rover1 on a private ROS domain, lets the rover settle, sends an `identify` goal, and
compares the result with the simulator's latched truth on /sim/rover1/parameters.
"""
from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np
import rclpy
from rclpy.action import ActionClient
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from coop_common.dynparams import PARAM_NAMES
from coop_common.lockstep_node import Lockstep, Pacer, remap_args
from coop_common.node_util import stamp
from coop_common.params import choice
from coop_common.qos import LATCHED_QOS
from coop_common.testing import NodeProcess, isolate_ros_environment
from coop_msgs.action import Identify
from coop_msgs.msg import DynamicParameters
from rover_sim.config import Integrator

from .errors import CoopIdError
from .excitation import Strategy

#: this client's node name (a lockstep participant), and rover_sim's lockstep round (s): 20 ms,
#: half the round trips of 10 ms (the arm's commands lead their time by command_lead_s)
CLIENT = 'table_2_1_sim'
ROUND_S = 0.02


def run_sim_identification(*, duration_s: float, strategy: Strategy | str, noise: float,
                           settle_s: float = 3.0, timeout_s: float = 600.0,
                           domain_id: int | None = None, log_dir: Path | None = None,
                           integrator: Integrator | str = Integrator.EXPLICIT,
                           lockstep: bool = False) -> dict:
    """domain_id: the ROS domain of the run (default: $COOP_SIM_DOMAIN_ID, else one from the
    pid); the processes started inherit it. log_dir: where the nodes' logs go (default: a new
    temporary directory). integrator: the simulator's (rover_sim `integrator` parameter).
    lockstep: the simulator steps no round before the identifier and this client have answered
    the last (docs/design.md), and the client holds it while the goal is sent: the same
    estimate on an idle and on a busy machine. An unknown strategy or integrator is refused
    (CoopIdError naming the choices) before anything starts."""
    strategy = choice(Strategy, strategy, 'strategy', error=CoopIdError)
    integrator = choice(Integrator, integrator, 'integrator', error=CoopIdError)
    if domain_id is None:
        domain_id = int(os.environ.get('COOP_SIM_DOMAIN_ID', '0')) or None
    isolate_ros_environment(domain_id)
    logs = Path(log_dir) if log_dir is not None else Path(
        tempfile.mkdtemp(prefix='coop_id_sim_'))
    logs.mkdir(parents=True, exist_ok=True)
    sim_args = ['-p', 'rovers:=1', '-p', 'stereo_rate_hz:=0.0', '-p', f'noise_fraction:={noise}',
                '-p', f'integrator:={integrator.value}']
    ident_args = ['-r', '__ns:=/rover1']
    if lockstep:
        # as fast as the identifier answers: nothing else closes a loop on the simulator
        sim_args += ['-p', f'lockstep_participants:=[rover1/identifier,{CLIENT}]',
                     '-p', f'lockstep_period_s:={ROUND_S}', '-p', 'real_time_factor:=0.0']
        ident_args += ['-p', 'lockstep:=true', '-p', 'use_sim_time:=true', *remap_args()]
    with NodeProcess('rover_sim', 'sim', sim_args, log_path=logs / 'sim.log'), \
            NodeProcess('coop_id', 'identifier', ident_args, log_path=logs / 'identifier.log'):
        ctx = Context()
        rclpy.init(context=ctx)
        node = Node(CLIENT, context=ctx)
        pacer_ls = Lockstep(node, lockstep)
        pacer = Pacer(pacer_ls)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        truth: list[DynamicParameters] = []
        node.create_subscription(DynamicParameters, '/sim/rover1/parameters', truth.append,
                                 LATCHED_QOS)
        client = ActionClient(node, Identify, '/rover1/identifier/identify')

        def spin_until(done, seconds: float, what: str) -> None:
            t0 = time.monotonic()
            while not done():
                ex.spin_once(timeout_sec=0.05)
                if time.monotonic() - t0 > seconds:
                    raise RuntimeError(f'no {what} in {seconds:g} s (logs in {logs})')
        try:
            if not client.wait_for_server(timeout_sec=60):
                raise RuntimeError(f'identifier action server not found (logs in {logs})')
            spin_until(lambda: truth, 60, '/sim/rover1/parameters')
            if lockstep:        # rest before the goal, then hold the sim while it is sent
                pacer.run(round(settle_s / ROUND_S))
                spin_until(lambda: pacer.paused, 60 + 20 * settle_s, 'rest before the goal')
            else:
                t0 = time.monotonic()
                spin_until(lambda: time.monotonic() - t0 >= settle_s, settle_s + 1, 'rest')
            # in lockstep the goal carries the round it is given in (the sim held there)
            goal = Identify.Goal(strategy=strategy.value, duration_s=duration_s)
            if lockstep:
                goal.stamp = stamp(pacer_ls.stamp_s)
            fut = client.send_goal_async(goal)
            spin_until(fut.done, 30, 'answer to the goal')
            handle = fut.result()
            if handle is None or not handle.accepted:
                raise RuntimeError('goal rejected')
            res_fut = handle.get_result_async()
            pacer.run()
            spin_until(res_fut.done, timeout_s, 'identification in time')
            res = res_fut.result().result
        finally:
            ex.shutdown()
            node.destroy_node()
            rclpy.try_shutdown(context=ctx)
    t = dict(zip(truth[-1].names, truth[-1].values, strict=False))
    x = np.array([t[n] for n in PARAM_NAMES])
    est = dict(zip(res.estimate.names, res.estimate.values, strict=False))
    v = np.array([est[n] for n in PARAM_NAMES])
    nz = x != 0
    return {'success': bool(res.success), 'message': res.message, 'truth': x, 'estimate': v,
            'std': np.array(res.estimate.std_devs), 'observable': list(res.estimate.observable),
            'mean_abs_rel_error': float(np.mean(np.abs(v[nz] - x[nz]) / np.abs(x[nz]))),
            'samples': int(res.estimate.samples), 'rejected': int(res.estimate.rejected_samples),
            'logs': str(logs)}
