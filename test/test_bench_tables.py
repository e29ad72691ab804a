"""The benchmarks print their tables through a function of the JSON they write, the function
docs/results makes the page's table with (tools/results_pages.py): hand-built results, and a
small run where one is fast."""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))       # `bench.*` as tools/results_pages.py imports them


def test_nbv_rate_table_of_a_hand_built_result():
    from bench.nbv_rate import format_table
    res = {'rows': [{'what': 'NI scoring 3-D, 24x18 rays, 0.1 m steps', 'poses_per_s': 674.2,
                     'peer_one_at_a_time_poses_per_s': 389.0, 'speedup': 1.733},
                    {'what': 'NBV decision 3-D (40 positions x 8 headings, 24x18 rays), all '
                             'included', 'seconds': 0.9034},
                    {'what': "task placement 3-D, node defaults, 8 targets' first requests: "
                             'median', 'seconds': 0.041, 'max_seconds': 0.067,
                     'outcomes': {'placed': 8}}],
           'task_placement_3d_outcomes': {'placed': 8}, 'load_average': [1.62, 3.4, 2.9],
           'cpus': 2}
    lines = format_table(res).splitlines()
    assert lines[0].split() == ['benchmark', 'poses/s', 'peer/s', 'ratio', 'seconds']
    assert lines[1].split()[-4:] == ['674', '389', '1.7', 'nan']
    assert lines[2].split()[-4:] == ['nan', 'nan', 'nan', '0.903']
    assert lines[4] == "task placement 3-D outcomes: {'placed': 8}"
    assert lines[5] == 'load average at the end 1.6, 3.4, 2.9 (1, 5, 15 min), 2 cores'


def _surface(ratio: float) -> dict:
    return {'voxels': 10, 'rms_ours_m': 0.02 * ratio, 'rms_octomap_m': 0.02,
            'rms_ours_literal_eq_3_10_m': 0.021, 'ratio': ratio,
            'ratio_per_offset': [ratio - 0.1, ratio + 0.1], 'rms_ours_kernel_m': 0.015,
            'rms_octomap_kernel_m': 0.018, 'kernel_ratio': 0.75,
            'kernel_ratio_per_offset': [0.7, 0.8]}


def _data(rate: float) -> dict:
    se = {'all': _surface(1.0) | {'off_surface_share_of_octomap_mse': 0.986},
          'surface': _surface(0.69) | {'by_range': [
              {'range_m': [0.0, 3.0], 'voxels': 3720, 'rms_ours_m': 0.0093,
               'rms_octomap_m': 0.0352, 'rms_ours_kernel_m': 0.013, 'ratio': 0.26,
               'kernel_ratio': 0.37}]},
          'near': _surface(0.26)}
    return {'ours_points_per_s': rate, 'octomap_points_per_s': rate / 2, 'speedup': 2.0,
            'state_agreement': 0.99871, 'bytes_per_known_voxel': 32.0,
            'octomap_bytes_per_leaf': 32.7, 'frame_latency_ms': 163.3, 'surface_error': se}


def test_map_vs_octomap_table_of_a_hand_built_result():
    from bench.map_vs_octomap import format_table
    res = {'stereo_frames': 4, 'image': [640, 480], 'subpixel': 'shift4', 'full_width': True,
           'supersample': 1, 'stereo_points': 1161875, 'synthetic_scans': 3,
           'synthetic_points': 749435, 'repeats': 2, 'grid_offsets': 8,
           'kernel': {'bandwidth_voxels': 0.8, 'radius_voxels': 2},
           'resolutions': {'0.1': _data(1.2e6) | {
               'synthetic': _data(0.8e6), 'stereo': _data(1.8e6),
               'fused_vs_single_differ': 0.0}},
           'ray_subdivision': {'0.1/1': {'ours_points_per_s': 3.049e6,
                                         'state_agreement': 0.9913}}}
    lines = format_table(res).splitlines()
    assert lines[0] == ('stereo: 4 frames 640x480 (sub-pixel: shift4, full width), 1161875 '
                        'points; synthetic: 3 scans, 749435 points; best of 2')
    assert lines[2].split() == ['0.1', 'synthetic', '0.800', '0.400', '2.00', '0.9987', '32.0',
                                '163.3']
    assert lines[4].split()[:3] == ['0.1', 'all', '1.200']
    assert 'pooled over 8 placements' in lines[5] and 'bandwidth 0.8 voxel, radius 2' in lines[5]
    assert lines[8].split() == ['0.1', 'synthetic', 'surface', '10', '13.8', '20.0', '0.69',
                                '0.59-0.79', '21.0', '1.05', '15.0', '0.75', '0.70-0.80',
                                '18.0']
    assert lines[14].split()[:3] == ['res', 'm', '0-3']
    assert lines[15].split() == ['0.1', '3720', '9.3/35.2/13.0', '0.26', '0.37']
    assert lines[17].split() == ['0.1', 'synthetic', '98.6%', '0.000%', '32.7']
    assert lines[-1].split() == ['0.1', '1', '3.049', '0.9913']
    res['supersample'] = 3
    assert ', full width, rendered 3x3 per pixel)' in format_table(res).splitlines()[0]


def test_map_vs_octomap_prints_the_table_of_its_json(tmp_path, capsys):
    """A small run (160x120 frames, one 0.5 m resolution, one placement; a few seconds)."""
    pytest.importorskip('octomap')
    pytest.importorskip('pybullet')
    from bench.map_vs_octomap import format_table, main
    out = tmp_path / 'm.json'
    assert main(['--points', '2000', '--width', '160', '--height', '120', '--resolutions',
                 '0.5', '--grid-offsets', '1', '--repeats', '1', '--json', str(out)]) == 0
    printed = capsys.readouterr().out
    res = json.loads(out.read_text())
    assert printed == format_table(res) + '\n'
    assert set(res['resolutions']) == {'0.5'} and len(res['ray_subdivision']) == 4
    assert math.isclose(res['resolutions']['0.5']['bytes_per_known_voxel'], 32.0)


def test_attempt_rate_compose_table_of_a_hand_built_result():
    from bench.attempt_rate import format_compose_table

    def run(walls, rate, setup, peaks):
        return {'attempt_wall_s': {'median': sorted(walls)[len(walls) // 2], 'values': walls},
                'sim_per_wall': {'median': rate}, 'setup_wall_s': setup,
                'successes': len(peaks),
                'outcomes': [{'success': True, 'peak_force_n': f} for f in peaks]}
    res = run([80.0, 90.0, 70.0], 0.4, 60.0, [5.7, 5.6, 5.1])
    res['composed_run'] = run([72.0, 81.0, 63.0], 0.45, 55.0, [5.7, 5.6, 5.1])
    res['composed_wall_ratio'] = 0.9
    lines = format_compose_table(res).splitlines()
    assert lines[1].split()[-4:] == ['80.0', '0.40', '60', '3/3']
    assert lines[2].split()[-4:] == ['72.0', '0.45', '55', '3/3']
    assert lines[3].endswith('0.90; the same outcomes and peak forces: True')


def test_sim_reset_table_of_a_hand_built_result():
    from bench.sim_reset import format_table
    res = {'kept_worker': {'median': 0.31, 'max': 0.4}, 'new_worker': {'median': 1.24, 'max': 1.5},
           'ratio': 0.25, 'resets': 5}
    lines = format_table(res).splitlines()
    assert lines[1].split()[-2:] == ['0.310', '0.400']
    assert lines[2].split()[-2:] == ['1.240', '1.500']
    assert lines[3] == 'handed over / new, median: 0.25 (5 resets each)'


def test_link_table_of_a_hand_built_result():
    from bench.link import format_table
    off = {'frames': 40, 'points_per_frame': 49000.0, 'raw_kb_per_frame': 1763.1,
           'compact_kb_per_frame': 40.4, 'raw_mbit_per_s_per_rover': 56.4,
           'compact_mbit_per_s_per_rover': 1.29, 'compact_vs_raw_agreement': 1.0,
           'compact_vs_raw_mean_diff_mm': 0.115, 'contribution_ms_p50': 38.0}
    run = {'scans_in_map': {'rover1': 20, 'rover2': 20}, 'missing': {'rover1': 0, 'rover2': 0},
           'link_kb_per_frame': {'rover1': 45.2, 'rover2': 60.9},
           'link_mbit_per_s_at_4hz': {'rover1': 1.45, 'rover2': 1.95},
           'latency_ms_p50': 91.4, 'latency_ms_p99': 277.5, 'agreement_with_offline': 0.9999}
    res = {'rate_mbit': 2.0, 'cut_s': 10.0, 'offline': {'320x240': off},
           'network': {'compact': run, 'compact_cut': run, 'raw_unshaped': run,
                       'cut_vs_uncut_agreement': 0.9998, 'cut_vs_uncut_mean_diff_mm': 0.1}}
    lines = format_table(res).splitlines()
    assert lines[2] == ('| 320x240 | 40 | 49000 | 1763 | 40.4 | 56.4 | 1.29 | 100.000 % | '
                        '0.115 | 38 |')
    assert lines[6] == ('| compact | 20, 20 | 0, 0 | 45, 61 | 1.45, 1.95 | 91.4 / 277.5 | '
                        '99.990 % |')
    assert lines[-1].startswith('cut (10 s, rover1) vs uncut: 99.980 % voxel states')
