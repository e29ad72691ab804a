"""Rovers on separate computers (issue #35): network namespaces joined by shaped veth links,
DDS over them, a rover's link cut mid-mapping (coop_common.netns, coop_bringup.field_mapping).
Needs root (CI runs as root)."""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from coop_common.netns import FieldNetwork, NetnsError

pytestmark = [pytest.mark.graph,
              pytest.mark.skipif(os.geteuid() != 0, reason='network namespaces need root')]
BAG = Path(__file__).resolve().parents[1] / 'bags' / 'mapping_two_rovers'


def _ours() -> list[str]:
    out = subprocess.run(['ip', 'netns', 'list'], capture_output=True, text=True,
                         check=True).stdout
    return [ln.split()[0] for ln in out.splitlines()
            if re.match(rf'coop{os.getpid()}(x\d+)?-', ln)]


def test_hosts_reach_each_other_only_over_their_links_and_are_removed_on_error():
    with pytest.raises(RuntimeError, match='on purpose'), FieldNetwork(['a', 'b']) as net:
        assert sorted(_ours()) == sorted([net.switch, net.ns('a'), net.ns('b')])
        # each host has its loopback and its link, nothing of this machine's network
        links = subprocess.run(['ip', 'netns', 'exec', net.ns('a'), 'ip', '-o', 'link'],
                               capture_output=True, text=True, check=True).stdout
        assert [ln.split(':')[1].strip().split('@')[0] for ln in links.splitlines()] == \
            ['lo', 'eth0']
        # a UDP datagram from a to b crosses a's link, and not while it is cut
        listen = net.start('b', ['python3', '-c',
                                 'import socket;s=socket.socket(2,2);s.bind(("",9999));'
                                 's.settimeout(20);print(s.recvfrom(64)[0].decode())'])
        send = ['python3', '-c', 'import socket,time\nfor i in range(100):\n'
                f' socket.socket(2,2).sendto(b"hello",("{net.address("b")}",9999));'
                'time.sleep(0.05)']
        net.cut('a')
        before = net.link_bytes()['a']['sent']
        net.start('a', send).wait(20)
        assert listen.poll() is None                 # nothing came through the cut
        assert net.link_bytes()['a']['sent'] == before
        net.restore('a')
        net.start('a', send)
        assert listen.wait(20) == 0                  # it got one (a timeout exits 1)
        assert net.link_bytes()['a']['sent'] > before
        raise RuntimeError('on purpose')
    assert _ours() == []


def test_a_terminated_run_leaves_no_namespace_and_no_process():
    """SIGTERM (a CI job's timeout) to a process that holds a network with a process on a
    host: both are gone once it has exited."""
    code = ('import time\nfrom coop_common.netns import FieldNetwork\n'
            "with FieldNetwork(['a']) as net:\n"
            "    p = net.start('a', ['sleep', '300'])\n"
            "    print(net.tag, p.pid, flush=True)\n"
            '    time.sleep(300)\n')
    proc = subprocess.Popen([sys.executable, '-c', code], stdout=subprocess.PIPE, text=True)
    tag, pid = proc.stdout.readline().split()
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(30) == 128 + signal.SIGTERM
    names = subprocess.run(['ip', 'netns', 'list'], capture_output=True, text=True,
                           check=True).stdout
    assert tag not in names
    with pytest.raises(ProcessLookupError):
        os.kill(int(pid), 0)


def test_host_names_are_checked():
    with pytest.raises(NetnsError, match='distinct'):
        FieldNetwork(['a', 'a'])
    with pytest.raises(NetnsError, match='host name'):
        FieldNetwork(['Rover-1'])


def test_two_rovers_map_through_shaped_links_and_one_cut(tmp_path):
    """Two rovers on hosts of their own send contributions over 2 Mbit/s links to the mapper on
    the base host; rover1's link goes down for 4 s mid-mapping. Every scan reaches the map
    once, the map is the offline map of the same bag, and what crossed a rover's link is a
    small part of its clouds (1.76 MB each)."""
    from coop_bringup.field_mapping import Cut, run, score, table
    if not (BAG / 'metadata.yaml').exists():
        pytest.skip('sample bag mapping_two_rovers not recorded')
    result, map_file = run(BAG, ['rover1', 'rover2'], out_dir=tmp_path, rate_mbit=2.0,
                           cuts=[Cut('rover1', 3.0, 4.0)], settle_s=40.0)
    score(result, map_file, BAG)
    print(table(result))
    assert _ours() == []
    logs = {p.name: p.read_text()[-3000:] for p in tmp_path.glob('*.log')}
    assert result.complete, f'{result.scans_in_map} of {result.frames_in_bag}: {logs}'
    cut_at = result.scans_at_cut[0]['scans']
    assert 0 < cut_at < result.frames_in_bag['rover1'], 'the cut came mid-mapping'
    assert result.missing == {'rover1': 0, 'rover2': 0}
    assert result.sessions == {'rover1': 1, 'rover2': 1}
    assert result.agreement_with_offline >= 0.999      # late scans fused in stamp order
    assert result.mean_diff_mm_max < 1.0
    for r in ('rover1', 'rover2'):
        assert result.link_bytes[r]['sent'] < 0.1 * 20 * 1.76e6


PUBLISH_CONTRIBUTIONS = """
import sys, time
import numpy as np
import rclpy
from std_msgs.msg import Header
from builtin_interfaces.msg import Time
from coop_common.qos import CONTRIBUTION_QOS
from coop_mapping.ros_conv import contribution_to_msg
from coop_mapping.voxelmap import VoxelMap
from coop_msgs.msg import MapContribution
ns, n, wait_s = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
rclpy.init()
node = rclpy.create_node('contributor', namespace=ns)
pub = node.create_publisher(MapContribution, 'map_contribution', CONTRIBUTION_QOS)
t_end = time.monotonic() + wait_s
while pub.get_subscription_count() == 0 and time.monotonic() < t_end:
    rclpy.spin_once(node, timeout_sec=0.1)
print('subscribers', pub.get_subscription_count(), flush=True)
rng = np.random.default_rng(1)
vm = VoxelMap(0.1)
for k in range(n):
    pts = np.c_[np.full(300, 3.0), rng.uniform(-1, 1, 300), rng.uniform(0, 1, 300)]
    c = vm.contribution(pts, np.array([0.0, 0.0, 0.8]))
    pub.publish(contribution_to_msg(c, vm, Header(stamp=Time(sec=k + 1), frame_id='map'),
                                    source='rover1', session=time.time_ns(), sequence=k + 1))
    rclpy.spin_once(node, timeout_sec=0.2)
time.sleep(2.0)
"""


def test_a_second_team_on_the_network_never_reaches_this_teams_map(tmp_path):
    """Team A's mapper (namespace /team_a) and a rover of each team on one network and domain:
    team B's rover1 finds no subscriber for its contributions and team A's map holds only team
    A's rover1's."""
    from coop_common.testing import executable_path, pick_domain_id
    from coop_mapping.voxelmap import MapFileError, VoxelMap
    map_file = tmp_path / 'team_a.cmap'
    with FieldNetwork(['base', 'rover_a', 'rover_b']) as net:
        env = net.ros_env(domain_id=pick_domain_id())
        net.start('base', [str(executable_path('coop_mapping', 'mapper')), '--ros-args',
                           '-r', '__ns:=/team_a', '-p', "rovers:=['rover1']",
                           '-p', 'map_input:=contributions', '-p', f'map_file:={map_file}',
                           '-p', 'autosave_period_s:=0.5'], env=env,
                  log=tmp_path / 'mapper.log')
        b_log = tmp_path / 'team_b.log'
        team_b = net.start('rover_b', [sys.executable, '-c', PUBLISH_CONTRIBUTIONS,
                                       '/team_b/rover1', '5', '15'], env=env, log=b_log)
        team_a = net.start('rover_a', [sys.executable, '-c', PUBLISH_CONTRIBUTIONS,
                                       '/team_a/rover1', '3', '30'], env=env,
                           log=tmp_path / 'team_a.log')
        assert team_a.wait(60) == 0 and team_b.wait(60) == 0

        def scans() -> dict:
            try:
                return dict(VoxelMap.load(map_file).contributions)
            except MapFileError:
                return {}
        from coop_common.testing import wait_for
        wait_for(lambda: scans() == {'rover1': 3}, 20.0, poll_s=0.2,
                 what="team A's three contributions in its map")
    assert 'subscribers 1' in (tmp_path / 'team_a.log').read_text()
    assert 'subscribers 0' in b_log.read_text()
    assert scans() == {'rover1': 3}
