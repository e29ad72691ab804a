r"""Rovers on separate computers mapping one site: each rover's data source and stereo node on a
host of its own, the team's mapper on a base station, joined by rate-limited links that can be
cut (coop_common.netns; root).

    sudo -E python -m coop_bringup.field_mapping --bag bags/mapping_two_rovers \
        --rate-mbit 2 --cut rover1:2:6 --json out/field.json

Each rover host plays its own rover's recorded streams from the bag (images, camera_info,
stereo/pose: raw sensor data that never leaves the rover) into its stereo node, reliable and
transient local at both ends (QoS overrides), so that no frame is lost on a busy host (a rover
given `--restart` keeps the best-effort streams of a camera); the base host
runs the mapper. A rover's link is limited to `--rate-mbit`, the base's to that times the number
of rovers (the base's radio serves them all). What crosses a rover's link is what the mapper
subscribes: the contributions (`--map-input contributions`, the default) or the clouds and
camera poses (`clouds`, to measure what raw clouds would cost). `--cut ROVER:AT:FOR` takes a
rover's link down AT seconds after the map's first scan from that rover, for FOR seconds;
`--restart ROVER:AT` kills its stereo node AT seconds after the map's first scan and starts it
again. When every player has finished and the map
holds what the stereo nodes sent (or `--settle-s` has passed), the mapper is stopped cleanly (it
saves its map and ledger) and the run reports, per rover: frames in the bag, scans in the map,
contributions missing, sessions, bytes over its link; and the map against the one built offline
from the same bag (coop_mapping.offline).
"""
from __future__ import annotations

import argparse
import ast
import json
import re
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

from coop_common.files import write_atomic
from coop_common.netns import FieldNetwork
from coop_common.qos import durable_overrides
from coop_common.testing import executable_path, pick_domain_id
from coop_mapping.offline import STEREO_TOPIC, map_from_bag, stereo_topics
from coop_mapping.voxelmap import MapFileError, VoxelMap, state_agreement
from rover_bag.bagio import bag_info

__all__ = ['Cut', 'FieldRun', 'format_json', 'main', 'run', 'score', 'table']



_DROPPED = re.compile(r'clouds the middleware dropped: (\{[^}]*\})')


@dataclass(frozen=True)
class Cut:
    """A rover's link down from `at_s` after the map's first scan from that rover, for `for_s`."""

    rover: str
    at_s: float
    for_s: float

    @classmethod
    def parse(cls, text: str) -> Cut:
        rover, at, dur = text.split(':')
        return cls(rover, float(at), float(dur))


@dataclass
class FieldRun:
    """What a run measured (the JSON)."""

    rovers: list[str]
    map_input: str
    rate_mbit: float | None
    cuts: list[dict]
    play_rate: float
    scans_at_cut: list[dict] = field(default_factory=list)
    restarts: list[dict] = field(default_factory=list)
    scans_in_map: dict[str, int] = field(default_factory=dict)
    frames_in_bag: dict[str, int] = field(default_factory=dict)
    missing: dict[str, int] = field(default_factory=dict)
    clouds_dropped: dict[str, int] = field(default_factory=dict)
    sessions: dict[str, int] = field(default_factory=dict)
    link_bytes: dict[str, dict[str, int]] = field(default_factory=dict)
    link_mbit_per_s: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0
    voxels: int = 0
    offline_voxels: int = 0
    agreement_with_offline: float = float('nan')
    mean_diff_mm_max: float = float('nan')
    complete: bool = False


def _node(package: str, exe: str, ros_args: list[str], args: list[str] | None = None
          ) -> list[str]:
    return [str(executable_path(package, exe)), *(args or []), '--ros-args', *ros_args]


def run(bag: Path, rovers: list[str], *, out_dir: Path, map_input: str = 'contributions',
        rate_mbit: float | None = 2.0, cuts: Sequence[Cut] = (),
        restarts: Sequence[tuple[str, float]] = (), play_rate: float = 0.5,
        settle_s: float = 60.0, domain_id: int | None = None) -> tuple[FieldRun, Path]:
    """One run (the module docstring); returns the measurements and the mapper's saved map.
    `restarts`: (rover, at_s): its stereo node is killed (SIGKILL) at_s after the map's first
    scan and started again at once; the frames in between are not ranged."""
    info = bag_info(bag)
    frames = {r: info.topics[f'/{r}/stereo/left/image_raw'].count for r in rovers
              if f'/{r}/stereo/left/image_raw' in info.topics}
    if set(frames) != set(rovers):
        raise ValueError(f'{bag} has stereo for {sorted(frames)}, not {rovers}')
    for c in cuts:
        if c.rover not in rovers:
            raise ValueError(f'cut of {c.rover}: not a rover of this run')
    out_dir.mkdir(parents=True, exist_ok=True)
    map_file = out_dir / 'field_map.cmap'
    map_file.unlink(missing_ok=True)
    for log in out_dir.glob('*.log'):      # the processes append: this run's only
        log.unlink()
    result = FieldRun(rovers=list(rovers), map_input=map_input, rate_mbit=rate_mbit,
                      cuts=[asdict(c) for c in cuts], play_rate=play_rate,
                      frames_in_bag=frames)
    contribute = map_input == 'contributions'
    # the base's radio serves every rover: its link carries their sum
    base_rate = {'base': rate_mbit * len(rovers)} if rate_mbit is not None else {}
    with FieldNetwork(['base', *rovers], rate_mbit=rate_mbit, rates_mbit=base_rate) as net:
        env = net.ros_env(domain_id=pick_domain_id() if domain_id is None else domain_id)
        rl = '[' + ','.join(f"'{r}'" for r in rovers) + ']'
        mapper = net.start('base', _node('coop_mapping', 'mapper', [
            '-p', f'rovers:={rl}', '-p', f'map_input:={map_input}',
            '-p', f'map_file:={map_file}', '-p', 'autosave_period_s:=1.0',
            '-p', 'publish_period_s:=1.0']), env=env, log=out_dir / 'mapper.log')
        stereo, players = {}, {}

        restarted = {r for r, _ in restarts}

        def durable(r: str, endpoint: Literal['publisher', 'subscription']) -> list[str]:
            """A rover's camera streams reliable and transient local at both ends: at any
            load, its stereo node gets every frame. Not for a rover whose node restarts: a
            camera does not send a restarted node the frames it missed, nor may the replay."""
            return [] if r in restarted else durable_overrides(stereo_topics([r]), endpoint)

        def start_stereo(r: str) -> None:
            stereo[r] = net.start(r, _node('coop_mapping', 'stereo', [
                '-r', f'__ns:=/{r}', '-p', f'contribute:={contribute}',
                *durable(r, 'subscription')]), env=env, log=out_dir / f'stereo_{r}.log')
        for r in rovers:
            start_stereo(r)
        kills = sorted(restarts, key=lambda k: k[1])
        for r in rovers:
            topics = '[' + ','.join(f"'{t}'" for t in stereo_topics([r])
                                    if t in info.topics) + ']'
            players[r] = net.start(r, _node('rover_bag', 'play', [
                '-p', f'topics:={topics}', '-p', f'rate:={play_rate}',
                '-p', 'publish_clock:=false', '-p', 'wait_for_subscribers_s:=60.0',
                *durable(r, 'publisher')],
                [str(bag)]), env=env, log=out_dir / f'play_{r}.log')
        before = net.link_bytes()
        t0 = time.monotonic()
        pending = sorted(cuts, key=lambda c: c.at_s)
        down: list[tuple[float, str]] = []
        expected = dict(frames)

        read: dict = {'mtime': None, 'scans': {}}

        def map_scans() -> dict[str, int]:
            """The scans per rover in the mapper's autosave, read again only when it changed."""
            try:
                mtime = map_file.stat().st_mtime_ns
                if mtime != read['mtime']:
                    read.update(mtime=mtime, scans=dict(VoxelMap.load(map_file).contributions))
            except (OSError, MapFileError):
                pass
            return read['scans']
        t_played = t_mapping = None
        t_first: dict[str, float] = {}
        while True:
            now = time.monotonic()
            scans = map_scans()
            if t_mapping is None and scans:
                t_mapping = now            # the restarts count from the first scan in the map
            for r, n in scans.items():     # a cut counts from its rover's first scan in it
                if n:
                    t_first.setdefault(r, now)
            for c in [c for c in pending
                      if c.rover in t_first and c.at_s <= now - t_first[c.rover]]:
                pending.remove(c)
                net.cut(c.rover)
                result.scans_at_cut.append({'rover': c.rover, 'scans': scans.get(c.rover, 0)})
                down.append((now + c.for_s, c.rover))
            while t_mapping is not None and kills and kills[0][1] <= now - t_mapping:
                r = kills.pop(0)[0]
                stereo[r].kill()
                stereo[r].wait(10.0)
                result.restarts.append({'rover': r, 'scans': scans.get(r, 0)})
                start_stereo(r)
            for until, r in list(down):
                if until <= now:
                    net.restore(r)
                    down.remove((until, r))
            if t_played is None and all(p.poll() is not None for p in players.values()):
                t_played = now
            if t_played is not None and not pending and not down and not kills and (
                    scans == expected or now - t_played > settle_s):
                break
            if mapper.poll() is not None:
                raise RuntimeError(f'the mapper stopped (see {out_dir / "mapper.log"})')
            time.sleep(0.2)
        result.seconds = time.monotonic() - t0
        after = net.link_bytes()
        mapper.send_signal(signal.SIGINT)      # ip netns exec passes it on: a clean stop
        try:
            mapper.wait(30.0)
        except subprocess.TimeoutExpired:
            mapper.kill()
        for r in rovers:
            stereo[r].send_signal(signal.SIGINT)
        for r in rovers:
            try:
                stereo[r].wait(15.0)
            except subprocess.TimeoutExpired:
                stereo[r].kill()
    # the mapper's count of the clouds the middleware dropped (map_input clouds), from its
    # clean stop's log line
    found = _DROPPED.findall((out_dir / 'mapper.log').read_text(errors='replace'))
    result.clouds_dropped = {r: 0 for r in rovers} if map_input == 'clouds' else {}
    if found and map_input == 'clouds':
        result.clouds_dropped.update(ast.literal_eval(found[-1]))
    for h in after:
        result.link_bytes[h] = {k: after[h][k] - before[h][k] for k in after[h]}
    for r in rovers:
        result.link_mbit_per_s[r] = 8e-6 * result.link_bytes[r]['sent'] / max(
            result.seconds, 1e-9)
    return result, map_file


def score(result: FieldRun, map_file: Path, bag: Path) -> None:
    """Fill the map figures: scans and ledger per rover, agreement with the offline map."""
    vm = VoxelMap.load(map_file)
    result.scans_in_map = {r: int(vm.contributions.get(r, 0)) for r in result.rovers}
    for r in result.rovers:
        rec = vm.ledger.sources.get(r)
        result.missing[r] = rec.missing if rec else 0
        result.sessions[r] = rec.sessions if rec else 0
    off = map_from_bag(bag, result.rovers).map
    result.voxels, result.offline_voxels = len(vm), len(off)
    result.agreement_with_offline = state_agreement(vm.keys, vm.states(), off.keys,
                                                    off.states())
    result.mean_diff_mm_max = 1e3 * vm.largest_mean_distance(off)
    result.complete = result.scans_in_map == result.frames_in_bag


def table(result: FieldRun) -> str:
    """The run as a markdown table and a summary line."""
    lines = ['| rover | frames in bag | scans in map | missing | sessions | sent MB | '
             'received MB | Mbit/s sent |', '|---|---|---|---|---|---|---|---|']
    for r in result.rovers:
        b = result.link_bytes.get(r, {'sent': 0, 'received': 0})
        lines.append(f"| {r} | {result.frames_in_bag[r]} | {result.scans_in_map.get(r, 0)} | "
                     f"{result.missing.get(r, 0)} | {result.sessions.get(r, 0)} | "
                     f"{b['sent'] / 1e6:.2f} | {b['received'] / 1e6:.2f} | "
                     f'{result.link_mbit_per_s.get(r, 0):.2f} |')
    lines.append('')
    if result.clouds_dropped:
        lines.append(f"clouds the middleware dropped (the mapper's count from the writers' "
                     f'sequence numbers): {result.clouds_dropped}')
    if result.restarts:
        lines.append('restarts (stereo node killed and started again, with the scans in the '
                     f'map then): {result.restarts}')
    lines.append(f'{result.map_input}, links {result.rate_mbit} Mbit/s, cuts {result.cuts}: '
                 f'{result.voxels} voxels ({result.offline_voxels} offline), agreement with '
                 f'the offline map {100 * result.agreement_with_offline:.3f} %, merged means '
                 f'within {result.mean_diff_mm_max:.3f} mm; {result.seconds:.1f} s')
    return '\n'.join(lines)


def format_json(d: dict) -> str:
    """`table` of a run's JSON (docs/results)."""
    return table(FieldRun(**d))


def main(argv: list[str] | None = None) -> int:
    """`python -m coop_bringup.field_mapping` (the module docstring); exit 1 when the map does
    not hold every scan."""
    ap = argparse.ArgumentParser(prog='field_mapping', description=__doc__.split('\n\n')[0])
    ap.add_argument('--bag', type=Path, default=Path('bags/mapping_two_rovers'))
    ap.add_argument('--rovers', nargs='+', default=None,
                    help='rovers of the bag (default: every rover with stereo in it)')
    ap.add_argument('--map-input', choices=['contributions', 'clouds'],
                    default='contributions')
    ap.add_argument('--rate-mbit', type=float, default=2.0,
                    help="every link's rate limit (0: none)")
    ap.add_argument('--cut', type=Cut.parse, action='append', default=[],
                    metavar='ROVER:AT_S:FOR_S')
    ap.add_argument('--restart', action='append', default=[], metavar='ROVER:AT_S',
                    type=lambda t: (t.split(':')[0], float(t.split(':')[1])),
                    help="kill the rover's stereo node AT_S after the first scan and start it "
                    'again')
    ap.add_argument('--play-rate', type=float, default=0.5)
    ap.add_argument('--settle-s', type=float, default=60.0)
    ap.add_argument('--out', type=Path, default=None, help='logs and the map (default: a '
                    'temporary directory)')
    ap.add_argument('--json', type=Path, default=None)
    a = ap.parse_args(argv)
    rovers = a.rovers or sorted({m['rover'] for t in bag_info(a.bag).topics
                                 if (m := STEREO_TOPIC.match(t)) and t.endswith('left/image_raw')})
    with tempfile.TemporaryDirectory(prefix='field_mapping_') as tmp:
        out = a.out or Path(tmp)
        result, map_file = run(a.bag, rovers, out_dir=out, map_input=a.map_input,
                               rate_mbit=a.rate_mbit or None, cuts=a.cut, restarts=a.restart,
                               play_rate=a.play_rate, settle_s=a.settle_s)
        score(result, map_file, a.bag)
    print(table(result))
    if a.json:
        write_atomic(a.json, 'w', lambda f: json.dump(asdict(result), f, indent=1))
    return 0 if result.complete else 1


if __name__ == '__main__':
    sys.exit(main())
