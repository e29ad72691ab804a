"""The whole mission, shortened, end to end over DDS (issue #23): `coop_bringup.mission` with
the rovers starting by the site, 4 s of identification and the map from where they stand (one
next-best-view scan if the coverage needs it), each checked against the simulator's truth: the
identified parameters, the site's jaws in the saved map; and the run's MCAP bag, read back. The
insertion through the same nodes is `test_insertion_graph.py` (the master's camera pinned in
front of the site); the placement by `task_view` needs the map of a longer exploration than a
test affords (`coop_insertion table_5_1`, docs/results/insertion.md)."""
from __future__ import annotations

import json
import os
import socket

import pytest

pytestmark = pytest.mark.graph


def test_a_short_mission_identifies_and_maps(tmp_path):
    from coop_bringup.mission import Mission, MissionConfig
    from coop_bringup.report import top_view

    from coop_mapping.voxelmap import VoxelMap, unpack_keys

    with socket.socket() as s:                # the live view on a free port
        s.bind(('127.0.0.1', 0))
        port = s.getsockname()[1]
    cfg = MissionConfig(seed=1, occlusion_density=0.05, slot_in=5.0, identify_s=4.0,
                        coverage_target=0.5, max_scans=1, near_start=True,
                        phases=('identify', 'map'), live_port=port)
    rep = Mission(cfg, tmp_path, run_id='short', domain_id=int(os.environ['ROS_DOMAIN_ID']),
                  log=print).run()
    out = tmp_path / 'short'
    print((out / 'report.md').read_text())
    on_disk = json.loads((out / 'report.json').read_text())
    assert on_disk['insertion']['success'] is False          # not run: false, never missing
    status = {p['name']: (p['status'], p['reason']) for p in rep['phases']}
    assert status['identify'][0] == 'ok' and status['map'][0] == 'ok', status
    assert status['place'] == ('skipped', 'not asked for'), status
    assert rep['success']
    # identify: both rovers against the sim's truth (4 s of excitation: the inertias scatter,
    # the mass and the c.g. do not)
    for rover, r in rep['identification']['rovers'].items():
        p = {q['name']: q for q in r['params']}
        assert p['mass']['rel_error'] <= 0.05, (rover, p['mass'])
        assert all(p[n]['rel_error'] <= 0.1 for n in ('cg_y', 'cg_z')), rover
        assert r['mean_abs_rel_error'] <= 0.5, (rover, r['mean_abs_rel_error'])
    # map: the coverage target, and the site's jaws (truth: x 2.9..3.23, |y| <= 0.1) stand in
    # the saved map as obstacles
    assert rep['mapping']['coverage'] >= 0.5
    m = VoxelMap.load(out / 'team.cmap')
    top = top_view(unpack_keys(m.keys), m.probability(), m.resolution, centre_xy=(3.05, 0.0),
                   half_m=0.2)
    assert (top[:, 1:3] == 1).sum() >= 3, top
    for name in ('identification', 'coverage', 'map_top', 'map_3d'):
        assert (out / on_disk['plots'][name]).exists()
    # the bag of the run: closed by the runner, read offline, the mission's main topics in it
    # (the bulk streams left out by default)
    from rover_bag.bagio import read_messages
    bag = on_disk['bag']
    assert bag['closed'] and not bag['problems'] and bag['messages'] > 1000, bag
    for topic in ('/clock', '/map/grid', '/rover1/odom', '/rover2/odom', '/rover1/imu',
                  '/rover2/arm/wrench', '/rover1/dynamic_parameters',
                  '/rover2/dynamic_parameters', '/rover1/stereo/pose', '/sim/rover1/base_pose'):
        assert topic in bag['topics'], (topic, bag['topics'])
    assert not any(t.endswith(('/image_raw', '/stereo/points', '/map/voxels')) for t in
                   bag['topics'])
    grids = [m for _, _, _, m in read_messages(out / 'bag', ['/map/grid'])]
    assert grids and grids[-1].info.width * grids[-1].info.height > 0
    assert (grids[-1].data != -1).sum() > 0                       # something seen
    assert bag['size_mb'] < 50, bag['size_mb']
    assert 'Bag: `bag/`' in (out / 'report.md').read_text()
    # the live view ran through the whole mission (a node that dies fails the phase it broke;
    # what a client receives from it: test_live_view.py)
    assert on_disk['live_view']['url'] == f'ws://localhost:{port}'
    assert 'live view on ws://' in (out / 'logs' / 'live_view.log').read_text()
