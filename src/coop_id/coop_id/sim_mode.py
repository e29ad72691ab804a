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
from coop_common.qos import LATCHED_QOS
from coop_common.testing import NodeProcess, isolate_ros_environment
from coop_msgs.action import Identify
from coop_msgs.msg import DynamicParameters


def run_sim_identification(*, duration_s: float, strategy: str, noise: float,
                           settle_s: float = 3.0, timeout_s: float = 600.0,
                           domain_id: int | None = None, log_dir: Path | None = None,
                           integrator: str = 'explicit') -> dict:
    """domain_id: the ROS domain of the run (default: $COOP_SIM_DOMAIN_ID, else one from the
    pid); the processes started inherit it. log_dir: where the nodes' logs go (default: a new
    temporary directory). integrator: the simulator's (rover_sim `integrator` parameter)."""
    if domain_id is None:
        domain_id = int(os.environ.get('COOP_SIM_DOMAIN_ID', '0')) or None
    isolate_ros_environment(domain_id)
    logs = Path(log_dir) if log_dir is not None else Path(
        tempfile.mkdtemp(prefix='coop_id_sim_'))
    logs.mkdir(parents=True, exist_ok=True)
    sim_args = ['-p', 'rovers:=1', '-p', 'stereo_rate_hz:=0.0', '-p', f'noise_fraction:={noise}',
                '-p', f'integrator:={integrator}']
    with NodeProcess('rover_sim', 'sim', sim_args, log_path=logs / 'sim.log'), \
            NodeProcess('coop_id', 'identifier', ['-r', '__ns:=/rover1'],
                        log_path=logs / 'identifier.log'):
        ctx = Context()
        rclpy.init(context=ctx)
        node = Node('table_2_1_sim', context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        truth: list[DynamicParameters] = []
        node.create_subscription(DynamicParameters, '/sim/rover1/parameters', truth.append,
                                 LATCHED_QOS)
        client = ActionClient(node, Identify, '/rover1/identifier/identify')
        try:
            if not client.wait_for_server(timeout_sec=60):
                raise RuntimeError(f'identifier action server not found (logs in {logs})')
            t0 = time.monotonic()
            while time.monotonic() - t0 < settle_s or not truth:   # rest before the goal
                ex.spin_once(timeout_sec=0.05)
                if time.monotonic() - t0 > 60:
                    raise RuntimeError(f'no /sim/rover1/parameters (logs in {logs})')
            fut = client.send_goal_async(Identify.Goal(strategy=strategy, duration_s=duration_s))
            ex.spin_until_future_complete(fut, timeout_sec=30)
            handle = fut.result()
            if handle is None or not handle.accepted:
                raise RuntimeError('goal rejected')
            res_fut = handle.get_result_async()
            ex.spin_until_future_complete(res_fut, timeout_sec=timeout_s)
            if not res_fut.done():
                raise RuntimeError('identification did not finish in time')
            res = res_fut.result().result
        finally:
            ex.shutdown()
            node.destroy_node()
            rclpy.try_shutdown(context=ctx)
    t = dict(zip(truth[-1].names, truth[-1].values))
    x = np.array([t[n] for n in PARAM_NAMES])
    est = dict(zip(res.estimate.names, res.estimate.values))
    v = np.array([est[n] for n in PARAM_NAMES])
    nz = x != 0
    return {'success': bool(res.success), 'message': res.message, 'truth': x, 'estimate': v,
            'std': np.array(res.estimate.std_devs), 'observable': list(res.estimate.observable),
            'mean_abs_rel_error': float(np.mean(np.abs(v[nz] - x[nz]) / np.abs(x[nz]))),
            'samples': int(res.estimate.samples), 'rejected': int(res.estimate.rejected_samples),
            'logs': str(logs)}
