"""The team launch file run with the real `ros2 launch` (ros2cli and launch from
../shared/ros2-tools, which CI installs): the graph that comes up (node names, namespaces,
parameters, relative topic names), and Ctrl-C ending every node cleanly. Without the tools the
tests skip and say why; with COOP_REQUIRE_ROS2_TOOLS=1 (CI) they fail instead."""
from __future__ import annotations

import os
import re
import signal
import subprocess
import tempfile
import time
from pathlib import Path

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from visualization_msgs.msg import MarkerArray

from coop_common.qos import LATCHED_QOS
from coop_common.testing import pick_domain_id, ros2_tools, wait_for

pytestmark = pytest.mark.graph

TEAM_NODES = {'rover_sim', 'mapper', 'view_planner'}
ROVER_NODES = {'stereo', 'identifier'}


@pytest.fixture(scope='module')
def ros2():
    return ros2_tools()


class Launch:
    """`ros2 launch ...` in its own process group, output to a file."""

    def __init__(self, ros2: str, *args: str) -> None:
        self.log = Path(tempfile.mkstemp(prefix='launch_', suffix='.log')[1])
        self._out = self.log.open('w')
        # a fatal signal makes launch print every thread's stack (see wait())
        env = {**os.environ, 'PYTHONFAULTHANDLER': '1'}
        self.proc = subprocess.Popen([ros2, 'launch', 'coop_bringup', 'team.launch.py', *args],
                                     stdout=self._out, stderr=subprocess.STDOUT, env=env,
                                     start_new_session=True)

    def text(self) -> str:
        return self.log.read_text(errors='replace')

    def interrupt(self) -> None:
        """Ctrl-C as a terminal sends it: SIGINT to the whole process group."""
        os.killpg(self.proc.pid, signal.SIGINT)

    def wait(self, timeout_s: float = 30.0) -> int:
        """launch's exit code; on a timeout, what it printed and which of its processes live."""
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            try:
                ps = subprocess.run(['ps', '-o', 'pid,stat,etime,args', '--sid',
                                     str(self.proc.pid)],
                                    capture_output=True, text=True, check=False).stdout
            except OSError as e:
                ps = str(e)
            # the stacks, to the log: first of the nodes still alive (launch relays their
            # output), then of launch itself
            stuck = [int(line.split()[0]) for line in ps.splitlines()[1:]
                     if line.split() and int(line.split()[0]) != self.proc.pid]
            for pid in stuck:   # how each treats SIGINT (signal 2: bit 1 of the masks)
                try:
                    status = Path(f'/proc/{pid}/status').read_text()
                    ps += f'{pid}: ' + ' '.join(ln for ln in status.splitlines()
                                                if ln.startswith(('SigBlk', 'SigIgn',
                                                                  'SigCgt'))) + '\n'
                    os.kill(pid, signal.SIGABRT)
                except OSError:
                    pass
            if stuck:
                time.sleep(2.0)      # a fixed grace for launch to relay what they print
            os.kill(self.proc.pid, signal.SIGABRT)
            try:
                self.proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                pass
            raise AssertionError(f'launch still running {timeout_s} s after Ctrl-C; its '
                                 f'processes:\n{ps}\nits output:\n{self.text()[-8000:]}') from None

    def close(self) -> None:
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.proc.wait(timeout=10)
        self._out.close()
        self.log.unlink(missing_ok=True)


@pytest.fixture
def graph_node():
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(os.environ.get('ROS_DOMAIN_ID', pick_domain_id())))
    node = Node('launch_probe', context=ctx)
    node.executor_ = SingleThreadedExecutor(context=ctx)
    node.executor_.add_node(node)
    yield node
    node.executor_.shutdown()
    node.destroy_node()
    rclpy.shutdown(context=ctx)


def _nodes(node: Node) -> set[str]:
    return {f'{ns.rstrip("/")}/{name}' for name, ns in node.get_node_names_and_namespaces()}


def _param(node: Node, target: str, name: str):
    client = AsyncParameterClient(node, target)
    assert client.wait_for_services(timeout_sec=10.0), f'{target} has no parameter services'
    future = client.get_parameters([name])
    node.executor_.spin_until_future_complete(future, timeout_sec=10.0)
    return parameter_value_to_python(future.result().values[0])


def _group_gone(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return True
    return False


@pytest.mark.parametrize('team', ['', 'team_a'])
def test_team_launch_brings_up_the_graph_and_ctrl_c_ends_it_cleanly(ros2, graph_node, team):
    ns = f'/{team}' if team else ''
    want = ({f'{ns}/{n}' for n in TEAM_NODES}
            | {f'{ns}/{r}/{n}' for r in ('rover1', 'rover2') for n in ROVER_NODES})
    launch = Launch(ros2, *([f'team:={team}'] if team else []), 'seed:=4', 'rate:=1.0')
    try:
        wait_for(lambda: want <= _nodes(graph_node) or launch.proc.poll() is not None, 90.0,
                 spin=lambda dt: graph_node.executor_.spin_once(timeout_sec=dt),
                 what=f'the nodes of the team {team or "(root)"}')
        assert launch.proc.poll() is None, launch.text()[-3000:]
        assert want <= _nodes(graph_node)
        # launch arguments and the package's params file (keyed /**/<node>) both reach nodes
        assert _param(graph_node, f'{ns}/rover_sim', 'seed') == 4
        assert _param(graph_node, f'{ns}/rover_sim', 'rovers') == 2
        assert _param(graph_node, f'{ns}/view_planner', 'camera_height_m') == 0.75
        assert _param(graph_node, f'{ns}/mapper', 'rovers') == ['rover1', 'rover2']
        assert _param(graph_node, f'{ns}/rover2/identifier', 'use_sim_time') is True
        # every name relative: the team's map and the rovers' clouds are under its namespace
        topics = {t for t, _ in graph_node.get_topic_names_and_types()}
        assert {f'{ns}/map/voxels', f'{ns}/rover1/stereo/points',
                f'{ns}/rover2/dynamic_parameters', '/clock'} <= topics
        services = {s for s, _ in graph_node.get_service_names_and_types()}
        assert {f'{ns}/viewplan/next_best_view', f'{ns}/map/save', f'{ns}/sim/reset'} <= services

        launch.interrupt()
        code = launch.wait()
        text = launch.text()
        assert code == 0, text[-3000:]
        finished = set(re.findall(r'\[INFO\] \[([\w-]+)\]: process has finished cleanly', text))
        assert len(finished) == len(want), text[-3000:]
        assert 'process has died' not in text and 'Traceback' not in text, text[-3000:]
        wait_for(lambda: _group_gone(launch.proc.pid), 10.0, what='every launched process gone')
    finally:
        launch.close()


def test_bag_source_and_bad_arguments(ros2, graph_node):
    root = Path(__file__).resolve().parents[1]
    launch = Launch(ros2, 'source:=bag', f'bag:={root / "bags" / "mapping_two_rovers"}',
                    'identify:=false')
    try:
        want = {'/rover_bag_player', '/mapper', '/view_planner', '/rover1/stereo',
                '/rover2/stereo'}
        wait_for(lambda: want <= _nodes(graph_node) or launch.proc.poll() is not None, 90.0,
                 spin=lambda dt: graph_node.executor_.spin_once(timeout_sec=dt),
                 what='the bag-fed team')
        assert want <= _nodes(graph_node), launch.text()[-3000:]
        assert not {'/rover_sim', '/rover1/identifier'} & _nodes(graph_node)
    finally:
        launch.close()
    for args, why in ((['source:=bag'], 'needs bag:='),
                      (['rovers:=rover1 rover1'], 'distinct'),
                      (['rovers:=alpha'], 'the simulator names its rovers')):
        out = subprocess.run([ros2, 'launch', 'coop_bringup', 'team.launch.py', *args],
                             capture_output=True, text=True, timeout=60)
        assert out.returncode != 0 and why in out.stdout + out.stderr, (args, out.stdout[-2000:])


def test_two_teams_in_one_domain_do_not_cross_talk(ros2, graph_node):
    """team_a (seed 1) and team_b (seed 2) side by side, each on its own clock: every topic and
    service of a team is published, served and subscribed by that team's nodes only, and each
    team's world is its own."""
    teams = {'team_a': 1, 'team_b': 2}
    launches = [Launch(ros2, f'team:={t}', f'seed:={s}', 'clock:=team', 'identify:=false',
                       'rate:=0.5') for t, s in teams.items()]
    try:
        want = {f'/{t}/{n}' for t in teams for n in ('rover_sim', 'mapper', 'view_planner',
                                                      'rover1/stereo', 'rover2/stereo')}
        spin = lambda dt: graph_node.executor_.spin_once(timeout_sec=dt)  # noqa: E731
        wait_for(lambda: want <= _nodes(graph_node), 120.0, spin=spin, what='both teams')
        wait_for(lambda: {f'/{t}/rover1/stereo/points' for t in teams}
                 <= {n for n, _ in graph_node.get_topic_names_and_types()}, 60.0, spin=spin,
                 what="both teams' clouds")
        topics = [n for n, _ in graph_node.get_topic_names_and_types()]
        assert not graph_node.get_publishers_info_by_topic('/clock'), 'a team on the global clock'
        # no name of a team's node outside its namespace: an absolute name would show up here
        # (asked per node: other graphs in the domain, e.g. a parallel test run, do not count)
        for name, ns in graph_node.get_node_names_and_namespaces():
            team = ns.split('/')[1] if ns.count('/') >= 1 else ''
            if team not in teams:
                continue
            names = [t for t, _ in graph_node.get_publisher_names_and_types_by_node(name, ns)
                     + graph_node.get_subscriber_names_and_types_by_node(name, ns)]
            stray = [t for t in names if not t.startswith(f'/{team}/')
                     and t not in ('/rosout', '/parameter_events')]
            assert not stray, (f'{ns}/{name}', stray)
        for t in teams:
            ours = [n for n in topics if n.startswith(f'/{t}/')]
            assert f'/{t}/clock' in ours and f'/{t}/map/voxels' in ours
            subs = graph_node.get_subscriptions_info_by_topic(f'/{t}/rover2/stereo/points')
            assert any(i.node_name == 'mapper' and i.node_namespace == f'/{t}' for i in subs)
            for name in ours:
                for info in (graph_node.get_publishers_info_by_topic(name)
                             + graph_node.get_subscriptions_info_by_topic(name)):
                    if info.node_name == 'launch_probe':
                        continue
                    assert info.node_namespace.startswith(f'/{t}'), (name, info.node_namespace)
        # each team's own world (seeded differently), each served by its own simulator
        worlds = {}
        for t in teams:
            got = []
            graph_node.create_subscription(MarkerArray, f'/{t}/sim/world', got.append,
                                           LATCHED_QOS)
            wait_for(lambda: got, 30.0, spin=spin, what=f'{t}/sim/world')
            worlds[t] = len(got[-1].markers)
        assert worlds['team_a'] != worlds['team_b'], worlds
        for launch in launches:  # Ctrl-C in both terminals, then each ends
            launch.interrupt()
        for launch in launches:
            assert launch.wait() == 0, launch.text()[-3000:]
    finally:
        for launch in launches:
            launch.close()
