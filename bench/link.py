#!/usr/bin/env python3
"""Mapping over field radios: what crosses a rover's link, raw clouds against compact map
contributions, and the map each gives (issue #35).

1. per frame, offline (no DDS): each stereo frame of a two-rover bag ranged as the stereo node
   does; the serialized PointCloud2 + camera_pose a mapper would take (raw) against the
   serialized MapContribution (compact), as Mbit/s per rover at the bag's stereo rate; the map
   fused from the contributions as they arrive (decoded) against the map fused from the clouds.
   At the default 320x240 (bags/mapping_two_rovers) and at 640x480 (a bag recorded for the run
   from the simulator, --skip-640 to leave it out).
2. through the field network (coop_common.netns, root): the two-rover bag played on two rover
   hosts into their stereo nodes, the mapper on a base host, links shaped to --rate-mbit: the
   bytes each rover's link carried per frame (contributions, and the raw clouds with the links
   unshaped: 2 Mbit/s cannot carry them; the base's link is shaped to the rovers' sum), at the
   bag's own speed (--play-rate), the time from a contribution's publication to its
   map update, and the same run with rover1's link cut --cut-s mid-mapping: its map against
   the uncut one's.

    sudo -E bench/link.py --json out/bench/link.json
"""
from __future__ import annotations

import argparse
import os
import re
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import numpy as np
from coop_bringup.field_mapping import Cut, run, score
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.serialization import serialize_message
from std_msgs.msg import Header

from coop_common.cli import output_path
from coop_common.files import write_json
from coop_mapping.offline import MapSettings, frame_scan, stereo_frames, stereo_topics
from coop_mapping.ros_conv import cloud_to_msg, contribution_to_msg, msg_to_contribution
from coop_mapping.voxelmap import VoxelMap, state_agreement
from rover_bag.bagio import read_messages

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / 'bags' / 'mapping_two_rovers'
STEREO_HZ = 4.0
_LATENCY = re.compile(r'p50 ([\d.]+) ms, p99 ([\d.]+) ms')


def offline(bag: Path) -> dict:
    """Part 1 on one bag."""
    msgs = [(m.topic, m.msg) for m in read_messages(bag, stereo_topics(['rover1', 'rover2']))]
    frames = sorted(stereo_frames(msgs, ['rover1', 'rover2']), key=lambda f: (f.stamp_ns,
                                                                            f.rover))
    settings = MapSettings()
    raw_map, compact_map, maker = settings.new_map(), settings.new_map(), settings.new_map()
    raw_b = compact_b = n_points = 0
    t_contrib = []
    width = height = 0
    for fr in frames:
        pts, cov, origin = frame_scan(fr)
        n_points += len(pts)
        width, height = fr.left_info.width, fr.left_info.height
        hdr = Header(stamp=fr.left.header.stamp, frame_id='map')
        raw_b += len(serialize_message(cloud_to_msg(pts, cov, hdr)))
        raw_b += len(serialize_message(PoseWithCovarianceStamped(header=hdr)))  # camera_pose
        raw_map.insert_scan(pts, origin, covariances=cov)
        t0 = time.perf_counter()
        c = maker.contribution(pts, origin, covariances=cov)
        msg = contribution_to_msg(c, maker, hdr, source=fr.rover, session=1, sequence=1)
        t_contrib.append(time.perf_counter() - t0)
        compact_b += len(serialize_message(msg))
        compact_map.apply(msg_to_contribution(msg, compact_map))
    n = len(frames)
    return {
        'image': f'{width}x{height}', 'frames': n, 'points_per_frame': n_points / len(frames),
        'raw_kb_per_frame': raw_b / n / 1e3, 'compact_kb_per_frame': compact_b / n / 1e3,
        'raw_mbit_per_s_per_rover': raw_b / n * STEREO_HZ * 8e-6,
        'compact_mbit_per_s_per_rover': compact_b / n * STEREO_HZ * 8e-6,
        'compact_vs_raw_agreement': state_agreement(raw_map.keys, raw_map.states(),
                                                    compact_map.keys, compact_map.states()),
        'compact_vs_raw_mean_diff_mm': 1e3 * raw_map.largest_mean_distance(compact_map),
        'contribution_ms_p50': float(np.median(t_contrib) * 1e3),
    }


def record_640(out: Path) -> Path:
    """bags/mapping_two_rovers' run again with 640x480 images, into `out`."""
    sys.path.insert(0, str(ROOT / 'tools'))
    import record_sample_bags as rsb

    base = next(r for r in rsb.RUNS if r.name == 'mapping_two_rovers')
    run640 = rsb.Run('mapping_two_rovers_640', base.what, [*base.sim_args, '-p',
                                                            'image_width:=640', '-p',
                                                            'image_height:=480'],
                     base.topics, base.seconds, base.drive)
    with tempfile.TemporaryDirectory() as tmp:
        return rsb.record_run(run640, out, Path(tmp))


def network(rate_mbit: float, cut_s: float, out: Path, play_rate: float) -> dict:
    """Part 2."""
    res = {}
    runs = {'compact': ('contributions', rate_mbit, []),
            'compact_cut': ('contributions', rate_mbit, [Cut('rover1', 2.0, cut_s)]),
            'raw_unshaped': ('clouds', None, [])}
    maps = {}
    for name, (map_input, rate, cuts) in runs.items():
        d = out / name
        result, map_file = run(BAG, ['rover1', 'rover2'], out_dir=d, map_input=map_input,
                               rate_mbit=rate, cuts=cuts, settle_s=60.0,
                               play_rate=play_rate)
        score(result, map_file, BAG)
        maps[name] = VoxelMap.load(map_file)
        per_frame = {r: result.link_bytes[r]['sent'] / result.frames_in_bag[r]
                     for r in result.rovers}
        m = _LATENCY.search((d / 'mapper.log').read_text())
        res[name] = {
            'complete': result.complete, 'scans_in_map': result.scans_in_map,
            'missing': result.missing, 'sessions': result.sessions,
            'link_kb_per_frame': {r: v / 1e3 for r, v in per_frame.items()},
            'link_mbit_per_s_at_4hz': {r: v * STEREO_HZ * 8e-6 for r, v in per_frame.items()},
            'agreement_with_offline': result.agreement_with_offline,
            'scans_at_cut': result.scans_at_cut, 'seconds': result.seconds,
            'latency_ms_p50': float(m.group(1)) if m else None,
            'latency_ms_p99': float(m.group(2)) if m else None,
        }
    a, b = maps['compact'], maps['compact_cut']
    res['cut_vs_uncut_agreement'] = state_agreement(a.keys, a.states(), b.keys, b.states())
    res['cut_vs_uncut_mean_diff_mm'] = 1e3 * a.largest_mean_distance(b)
    return res


def format_table(out: dict) -> str:
    """The printed tables of a result (main's JSON)."""
    lines = ['| image | frames | points/frame | raw kB/frame | compact kB/frame | raw Mbit/s/'
             'rover | compact Mbit/s/rover | agreement | means within mm | contribution ms |',
             '|---|---|---|---|---|---|---|---|---|---|']
    for img, d in out['offline'].items():
        lines.append(
            f"| {img} | {d['frames']} | {d['points_per_frame']:.0f} | "
            f"{d['raw_kb_per_frame']:.0f} | {d['compact_kb_per_frame']:.1f} | "
            f"{d['raw_mbit_per_s_per_rover']:.1f} | {d['compact_mbit_per_s_per_rover']:.2f} | "
            f"{100 * d['compact_vs_raw_agreement']:.3f} % | "
            f"{d['compact_vs_raw_mean_diff_mm']:.3f} | {d['contribution_ms_p50']:.0f} |")
    net = out.get('network')
    if net:
        lines += ['', '| run | scans in map | missing | link kB/frame | Mbit/s at 4 Hz | '
                  'latency p50 / p99 ms | agreement with offline |',
                  '|---|---|---|---|---|---|---|']
        for name in ('compact', 'compact_cut', 'raw_unshaped'):
            r = net[name]
            kb = ', '.join(f'{v:.0f}' for v in r['link_kb_per_frame'].values())
            mb = ', '.join(f'{v:.2f}' for v in r['link_mbit_per_s_at_4hz'].values())
            scans = ', '.join(str(v) for v in r['scans_in_map'].values())
            missing = ', '.join(str(v) for v in r['missing'].values())
            lines.append(f"| {name} | {scans} | {missing} | {kb} | {mb} | "
                         f"{r['latency_ms_p50']} / {r['latency_ms_p99']} | "
                         f"{100 * r['agreement_with_offline']:.3f} % |")
        lines += ['', f"cut ({out['cut_s']:.0f} s, rover1) vs uncut: "
                  f"{100 * net['cut_vs_uncut_agreement']:.3f} % voxel states, merged means "
                  f"within {net['cut_vs_uncut_mean_diff_mm']:.3f} mm (per rover: rover1, "
                  f"rover2; rover links {out['rate_mbit']} Mbit/s, the base's twice that, "
                  f"raw_unshaped unlimited; bags at {out.get('play_rate', 1.0)}x)"]
    return '\n'.join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--json', type=output_path, help='write the figures here')
    ap.add_argument('--rate-mbit', type=float, default=2.0)
    ap.add_argument('--cut-s', type=float, default=10.0)
    ap.add_argument('--play-rate', type=float, default=0.5,
                    help='bag speed in part 2 (1: the stereo at its 4 Hz, which two stereo '
                    'nodes on two shared cores do not keep up with)')
    ap.add_argument('--skip-640', action='store_true')
    ap.add_argument('--skip-network', action='store_true')
    a = ap.parse_args()
    out: dict = {'rate_mbit': a.rate_mbit, 'cut_s': a.cut_s, 'stereo_hz': STEREO_HZ,
                 'play_rate': a.play_rate}
    with tempfile.TemporaryDirectory(prefix='bench_link_') as tmp:
        out['offline'] = {'320x240': offline(BAG)}
        if not a.skip_640:
            out['offline']['640x480'] = offline(record_640(Path(tmp)))
        if not a.skip_network:
            if os.geteuid() != 0:
                print('part 2 needs root: skipped', file=sys.stderr)
            else:
                out['network'] = network(a.rate_mbit, a.cut_s, Path(tmp) / 'net',
                                         a.play_rate)
    d = out['offline']['320x240']
    out['raw_mbit_per_s_per_rover'] = d['raw_mbit_per_s_per_rover']
    out['compact_mbit_per_s_per_rover'] = d['compact_mbit_per_s_per_rover']
    out['compact_vs_raw_agreement'] = d['compact_vs_raw_agreement']
    net = out.get('network')
    if net:
        out['cut_vs_uncut_agreement'] = net['cut_vs_uncut_agreement']
        out['latency_ms_p50'] = net['compact']['latency_ms_p50']
        out['latency_ms_p99'] = net['compact']['latency_ms_p99']
    print(format_table(out))
    if a.json:
        write_json(a.json, out)
    return 0


if __name__ == '__main__':
    sys.exit(main())
