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


def run_sim_identification(*, duration_s: float, strategy: str, noise: float,
                           settle_s: float = 3.0, timeout_s: float = 600.0) -> dict:
    import rclpy  # noqa: PLC0415 - only this mode needs ROS
    from rclpy.action import ActionClient  # noqa: PLC0415
    from rclpy.node import Node  # noqa: PLC0415

    from coop_common.dynparams import PARAM_NAMES  # noqa: PLC0415
    from coop_common.qos import LATCHED_QOS  # noqa: PLC0415
    from coop_common.testing import NodeProcess, isolate_ros_environment  # noqa: PLC0415
    from coop_msgs.action import Identify  # noqa: PLC0415
    from coop_msgs.msg import DynamicParameters  # noqa: PLC0415

    isolate_ros_environment(int(os.environ.get('COOP_SIM_DOMAIN_ID', '0')) or None)
    logs = Path(tempfile.mkdtemp(prefix='coop_id_sim_'))
    sim_args = ['-p', 'rovers:=1', '-p', 'stereo_rate_hz:=0.0', '-p', f'noise_fraction:={noise}']
    with NodeProcess('rover_sim', 'sim', sim_args, log_path=logs / 'sim.log'), \
            NodeProcess('coop_id', 'identifier', ['-r', '__ns:=/rover1'],
                        log_path=logs / 'identifier.log'):
        rclpy.init()
        node = Node('table_2_1_sim')
        truth: list[DynamicParameters] = []
        node.create_subscription(DynamicParameters, '/sim/rover1/parameters', truth.append,
                                 LATCHED_QOS)
        client = ActionClient(node, Identify, '/rover1/identifier/identify')
        try:
            if not client.wait_for_server(timeout_sec=60):
                raise RuntimeError(f'identifier action server not found (logs in {logs})')
            t0 = time.monotonic()
            while time.monotonic() - t0 < settle_s or not truth:   # rest before the goal
                rclpy.spin_once(node, timeout_sec=0.05)
                if time.monotonic() - t0 > 60:
                    raise RuntimeError(f'no /sim/rover1/parameters (logs in {logs})')
            fut = client.send_goal_async(Identify.Goal(strategy=strategy, duration_s=duration_s))
            rclpy.spin_until_future_complete(node, fut, timeout_sec=30)
            handle = fut.result()
            if handle is None or not handle.accepted:
                raise RuntimeError('goal rejected')
            res_fut = handle.get_result_async()
            rclpy.spin_until_future_complete(node, res_fut, timeout_sec=timeout_s)
            if not res_fut.done():
                raise RuntimeError('identification did not finish in time')
            res = res_fut.result().result
        finally:
            node.destroy_node()
            rclpy.try_shutdown()
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
