"""The team launch file run with the real `ros2 launch` (ros2cli and launch from
`make ros2-tools`, which CI installs): the graph that comes up (node names, namespaces,
parameters, relative topic names), its transform tree (/tf, /tf_static) read as a ROS user reads
it (`ros2 topic echo --once /tf_static`, every frame any topic stamps found under `map`), and
Ctrl-C ending every node cleanly. Without the tools the tests skip and say why; with
COOP_REQUIRE_ROS2_TOOLS=1 (CI) they fail instead."""
from __future__ import annotations

import contextlib
import json
import math
import os
import re
import signal
import subprocess
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import pytest
import rclpy
import yaml
from coop_bringup.rig import stray_names, team_nodes
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from rosidl_runtime_py.utilities import get_message
from visualization_msgs.msg import MarkerArray

from coop_common.frames import RoverFrames
from coop_common.qos import LATCHED_QOS
from coop_common.testing import (
    NodeProcess,
    executable_path,
    pick_domain_id,
    ros2_tools,
    wait_for,
)
from coop_common.tf_tree import TF_QOS, TF_STATIC_LISTENER_QOS

pytestmark = pytest.mark.graph

TEAM_NODES = {'rover_sim', 'mapper', 'view_planner'}
ROVER_NODES = {'stereo', 'identifier', 'driver'}


@pytest.fixture(scope='module')
def ros2():
    """The `ros2` command. `ros2 action send_goal` (and other verbs that query the graph) start
    ros2cli's daemon for the domain, which outlives them: stopped once the tests are done."""
    tool = ros2_tools()
    yield tool
    subprocess.run([tool, 'daemon', 'stop'], check=False, capture_output=True, timeout=60)


class Launch:
    """`ros2 launch ...` in its own process group, output to a file."""

    def __init__(self, ros2: str, *args: str, file: str = 'team.launch.py') -> None:
        self.log = Path(tempfile.mkstemp(prefix='launch_', suffix='.log')[1])
        self._out = self.log.open('w')
        # a fatal signal makes launch print every thread's stack (see wait())
        env = {**os.environ, 'PYTHONFAULTHANDLER': '1'}
        self.proc = subprocess.Popen([ros2, 'launch', 'coop_bringup', file, *args],
                                     stdout=self._out, stderr=subprocess.STDOUT, env=env,
                                     start_new_session=True)

    def text(self) -> str:
        return self.log.read_text(errors='replace')

    def interrupt(self) -> None:
        """Ctrl-C as a terminal sends it: SIGINT to the whole process group."""
        os.killpg(self.proc.pid, signal.SIGINT)

    def wait(self, timeout_s: float = 30.0) -> int:
        """Launch's exit code; on a timeout, what it printed and which of its processes live."""
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
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(timeout=5.0)
            raise AssertionError(f'launch still running {timeout_s} s after Ctrl-C; its '
                                 f'processes:\n{ps}\nits output:\n{self.text()[-8000:]}') from None

    def close(self) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, signal.SIGKILL)
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
    # the node out of its executor and destroyed before the executor shuts down (the other
    # order segfaulted once in rclpy's destroy_node, after a launch's processes were killed)
    node.executor_.remove_node(node)
    node.destroy_node()
    node.executor_.shutdown()
    rclpy.shutdown(context=ctx)


def _nodes(node: Node) -> set[str]:
    return {f'{ns.rstrip("/")}/{name}' for name, ns in node.get_node_names_and_namespaces()}


def _param(node: Node, target: str, name: str):
    client = AsyncParameterClient(node, target)
    assert client.wait_for_services(timeout_sec=10.0), f'{target} has no parameter services'
    future = client.get_parameters([name])
    # a whole team starting on two cores can keep a node from answering for a while
    node.executor_.spin_until_future_complete(future, timeout_sec=60.0)
    assert future.done() and future.result() is not None, f'{target} did not answer for {name}'
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
        assert _param(graph_node, f'{ns}/view_planner', 'camera_height_m') == 0.78
        assert _param(graph_node, f'{ns}/mapper', 'rovers') == ['rover1', 'rover2']
        assert _param(graph_node, f'{ns}/rover2/identifier', 'use_sim_time') is True
        # every name relative: the team's map and the rovers' clouds are under its namespace
        topics = {t for t, _ in graph_node.get_topic_names_and_types()}
        assert {f'{ns}/map/voxels', f'{ns}/rover1/stereo/points',
                f'{ns}/rover2/dynamic_parameters', '/clock'} <= topics
        services = {s for s, _ in graph_node.get_service_names_and_types()}
        assert {f'{ns}/viewplan/next_best_view', f'{ns}/map/save', f'{ns}/sim/reset'} <= services
        if team:
            _drive_from_the_command_line(ros2, graph_node, ns)

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


def _drive_from_the_command_line(ros2: str, graph_node: Node, ns: str) -> None:
    """As the coop_bringup README shows a launched team moved: `ros2 action send_goal` to
    rover1's drive_to_pose, 0.4 m ahead of where its odometry says it stands."""
    from nav_msgs.msg import Odometry
    from rclpy.action import get_action_names_and_types

    from coop_common.qos import SENSOR_QOS
    assert f'{ns}/rover1/drive_to_pose' in {a for a, _ in get_action_names_and_types(graph_node)}
    odom: list[Odometry] = []
    sub = graph_node.create_subscription(Odometry, f'{ns}/rover1/odom', odom.append, SENSOR_QOS)
    try:
        wait_for(lambda: bool(odom), 30.0, what="rover1's odometry",
                 spin=lambda dt: graph_node.executor_.spin_once(timeout_sec=dt))
    finally:
        graph_node.destroy_subscription(sub)
    p, q = odom[-1].pose.pose.position, odom[-1].pose.pose.orientation
    yaw = 2 * math.atan2(q.z, q.w)
    x, y = p.x + 0.4 * math.cos(yaw), p.y + 0.4 * math.sin(yaw)
    goal = (f'{{pose: {{header: {{frame_id: {ns[1:]}/map}}, pose: {{position: {{x: {x:.3f}, '
            f'y: {y:.3f}}}}}}}, ignore_heading: true}}')
    out = subprocess.run([ros2, 'action', 'send_goal', f'{ns}/rover1/drive_to_pose',
                          'coop_msgs/action/DriveToPose', goal], capture_output=True, text=True,
                         timeout=120, check=False)
    assert out.returncode == 0 and 'SUCCEEDED' in out.stdout, out.stdout[-3000:] + out.stderr


def test_mission_launch_brings_up_the_whole_mission_graph(ros2, graph_node):
    """mission.launch.py, as `coop_bringup mission` and the insertion rig start it: the data
    source, each rover's identifier and stereo node, the mapper, the view planner, the master
    and the slave, with the scenario's arguments and the one parameter file's settings."""
    ns = '/team_m'
    want = ({f'{ns}/{n}' for n in ('rover_sim', 'mapper', 'view_planner', 'master', 'slave')}
            | {f'{ns}/{r}/{n}' for r in ('rover1', 'rover2') for n in ROVER_NODES})
    launch = Launch(ros2, 'team:=team_m', 'seed:=5', 'slot_in:=4.375', 'render_workers:=0',
                    'cg_to_arm:=[0.1, 0.0, 0.2]', file='mission.launch.py')
    try:
        wait_for(lambda: want <= _nodes(graph_node) or launch.proc.poll() is not None, 90.0,
                 spin=lambda dt: graph_node.executor_.spin_once(timeout_sec=dt),
                 what="the mission's nodes")
        assert launch.proc.poll() is None, launch.text()[-3000:]
        assert want <= _nodes(graph_node), (want - _nodes(graph_node))
        assert _param(graph_node, f'{ns}/rover_sim', 'seed') == 5
        assert _param(graph_node, f'{ns}/master', 'seed') == 5
        assert abs(_param(graph_node, f'{ns}/slave', 'slot_width_m') - 4.375 * 0.0254) < 1e-9
        assert _param(graph_node, f'{ns}/slave', 'cg_to_arm') == [0.1, 0.0, 0.2]
        assert _param(graph_node, f'{ns}/view_planner', 'camera_height_m') == 0.78
        assert _param(graph_node, f'{ns}/view_planner', 'clearance_m') == 0.46
        assert _param(graph_node, f'{ns}/rover1/identifier', 'use_sim_time') is True
        assert _param(graph_node, f'{ns}/rover_sim', 'lockstep_participants') == ['']
        launch.interrupt()
        code = launch.wait()
        text = launch.text()
        assert code == 0, text[-3000:]
        assert 'Traceback' not in text, text[-3000:]
        wait_for(lambda: _group_gone(launch.proc.pid), 10.0, what='every launched process gone')
    finally:
        launch.close()
    for args, why in ((['source:=hw'], "give 'rover=port'"),
                      (['source:=bag', 'bag:=x', 'lockstep:=true'], 'source:=sim only'),
                      (['rovers:=1'], 'needs a master and a slave'),
                      (['stereo_rovers:=rover3'], 'not among'),
                      (['live_view:=maybe'], 'give true or false')):
        out = subprocess.run([ros2, 'launch', 'coop_bringup', 'mission.launch.py', *args],
                             capture_output=True, text=True, timeout=60, check=False)
        assert out.returncode != 0 and why in out.stdout + out.stderr, (args, out.stdout[-2000:])


def test_the_mission_runs_its_phases_on_a_launched_graph(ros2, graph_node, tmp_path):
    """`ros2 launch coop_bringup mission.launch.py`, then `ros2 run coop_bringup mission
    --attach` runs the phases against that graph (here the identification, in lockstep); a
    client whose scenario is not the launched one is refused with the argument to give."""
    mission = executable_path('coop_bringup', 'mission')
    launch = Launch(ros2, 'seed:=3', 'render_workers:=0', 'lockstep:=true',
                    'clients:=insertion_rig mission', file='mission.launch.py')
    try:
        want = {'/rover_sim', '/master', '/slave', '/mapper', '/view_planner',
                *(f'/{r}/{n}' for r in ('rover1', 'rover2') for n in ROVER_NODES)}
        wait_for(lambda: want <= _nodes(graph_node) or launch.proc.poll() is not None, 90.0,
                 spin=lambda dt: graph_node.executor_.spin_once(timeout_sec=dt),
                 what="the mission's nodes")
        assert launch.proc.poll() is None, launch.text()[-3000:]
        base = [str(mission), '--attach', '--lockstep', '--phases', 'identify', '--out',
                str(tmp_path)]
        out = subprocess.run([*base, '--seed', '4', '--run-id', 'wrong'], capture_output=True,
                             text=True, timeout=120, check=False)
        assert out.returncode != 0 and 'launch with seed:=4' in out.stdout + out.stderr, \
            out.stdout[-3000:] + out.stderr[-3000:]
        out = subprocess.run([*base, '--seed', '3', '--identify-s', '4', '--run-id', 'ok'],
                             capture_output=True, text=True, timeout=600, check=False)
        assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
        rep = json.loads((tmp_path / 'ok' / 'report.json').read_text())
        status = {ph['name']: ph['status'] for ph in rep['phases']}
        assert status['identify'] == 'ok' and rep['domain_id'] == int(os.environ['ROS_DOMAIN_ID'])
        assert rep['identification']['mean_abs_rel_error'] <= 0.5, rep['identification']
        launch.interrupt()
        assert launch.wait() == 0, launch.text()[-3000:]
    finally:
        launch.close()


def test_mission_launch_with_the_hardware_source_activates_each_bridge(ros2, tmp_path):
    """source:=hw: a `rover_hw bridge` per rover on the port hw_ports gives it, configured and
    activated by the launch file as it starts (here against `rover_hw emulator`): the rover's
    sensor streams flow with no one driving the lifecycle by hand."""
    from sensor_msgs.msg import Imu

    from coop_common.testing import Probe
    link = tmp_path / 'rover1_hw'
    with NodeProcess('rover_hw', 'emulator', args=['--link', str(link)],
                     log_path=tmp_path / 'emulator.log') as emu:
        wait_for(link.exists, 30.0, what='the emulator pty')
        launch = Launch(ros2, 'source:=hw', 'rovers:=1', f'hw_ports:=rover1={link}',
                        'identify:=false', 'mapping:=false', 'insertion:=false',
                        file='mission.launch.py')
        probe = Probe('hw_launch_probe')
        try:
            probe.listen(Imu, '/rover1/imu')
            probe.spin_until(lambda: probe.count('/rover1/imu') >= 50 or
                             launch.proc.poll() is not None, 60.0, 'the bridge active')
            assert probe.count('/rover1/imu') >= 50, launch.text()[-3000:] + emu.log_text()
            launch.interrupt()
            assert launch.wait() == 0, launch.text()[-3000:]
        finally:
            probe.close()
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
                      (['rovers:=alpha'], 'the simulator names its rovers'),
                      (['arm_feedforward:=true'], 'give identified, nominal, none or off'),
                      (['source:=hw', 'hw_ports:=rover1=/dev/null rover2=/dev/null',
                        'arm_feedforward:=identified'], 'source:=sim only')):
        out = subprocess.run([ros2, 'launch', 'coop_bringup', 'team.launch.py', *args],
                             check=False, capture_output=True, text=True, timeout=60)
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
        # (asked per node: other graphs in the domain, e.g. a parallel test run, do not count;
        # the mission's report makes the same check, coop_bringup.rig.stray_names)
        for t in teams:
            assert team_nodes(graph_node, f'/{t}'), t
            assert stray_names(graph_node, f'/{t}') == {}, t
        for t in teams:
            ours = [n for n in topics if n.startswith(f'/{t}/')]
            assert f'/{t}/clock' in ours and f'/{t}/map/voxels' in ours
            # (discovered apart from the node: on a loaded machine its endpoints come later)
            wait_for(lambda t=t: any(
                i.node_name == 'mapper' and i.node_namespace == f'/{t}'
                for i in graph_node.get_subscriptions_info_by_topic(f'/{t}/rover2/stereo/points')),
                60.0, spin=spin, what=f"{t}'s mapper on rover2's clouds")
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
            wait_for(lambda got=got: got, 30.0, spin=spin, what=f'{t}/sim/world')
            worlds[t] = len(got[-1].markers)
        assert worlds['team_a'] != worlds['team_b'], worlds
        # one /tf, two trees: every frame of each under its team's prefix, none shared
        tf2_msgs = pytest.importorskip('tf2_msgs.msg')
        seen: list = []
        graph_node.create_subscription(tf2_msgs.TFMessage, '/tf', lambda m: seen.extend(
            m.transforms), TF_QOS)
        graph_node.create_subscription(tf2_msgs.TFMessage, '/tf_static', lambda m: seen.extend(
            m.transforms), TF_STATIC_LISTENER_QOS)
        want_tf = {f'{t}/{r}/{link}' for t in teams for r in ('rover1', 'rover2')
                   for link in ('odom', 'base_link', 'mast_tilt_link',
                                'right_camera_optical_frame')}
        try:
            wait_for(lambda: want_tf <= {f.child_frame_id for f in seen}, 60.0, spin=spin,
                     what="both teams' trees")
        except TimeoutError as exc:
            raise AssertionError(f'{exc}: missing {want_tf - {f.child_frame_id for f in seen}}'
                                 ) from None
        by_team = {t: {n for f in seen for n in (f.header.frame_id, f.child_frame_id)
                       if n.startswith(f'{t}/')} for t in teams}
        assert 'team_a/map' in by_team['team_a'] and 'team_b/map' in by_team['team_b']
        assert all(n.startswith(('team_a/', 'team_b/')) for f in seen
                   for n in (f.header.frame_id, f.child_frame_id)), 'a frame of no team'
        for launch in launches:  # Ctrl-C in both terminals, then each ends
            launch.interrupt()
        for launch in launches:
            assert launch.wait() == 0, launch.text()[-3000:]
    finally:
        for launch in launches:
            launch.close()


ROVERS = ('rover1', 'rover2')
#: messages whose stamped frames are not read: they hold no frame of ours, and the images are
#: megabytes a second to deserialize for frames their camera_info also carries
SKIP_TYPES = ('sensor_msgs/msg/Image', 'rosgraph_msgs/msg/Clock', 'tf2_msgs/msg/TFMessage')


def _frames_in(msg, out: set[str], depth: int = 0) -> None:
    """Every `frame_id` and `child_frame_id` in `msg` (nested messages and lists of them)."""
    if depth > 4 or not hasattr(msg, 'get_fields_and_field_types'):
        return
    for name in msg.get_fields_and_field_types():
        value = getattr(msg, name)
        if name in ('frame_id', 'child_frame_id') and isinstance(value, str):
            if value:
                out.add(value)
        elif isinstance(value, list):
            for item in value[:50]:
                _frames_in(item, out, depth + 1)
        else:
            _frames_in(value, out, depth + 1)


def _reader_qos(node, topic: str) -> QoSProfile:
    """Best effort (matches any writer), transient local where every writer latches."""
    infos = node.get_publishers_info_by_topic(topic)
    latched = infos and all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                            for i in infos)
    return QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT,
                      durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                                  else DurabilityPolicy.VOLATILE))


def test_the_team_publishes_one_tree_that_holds_every_stamped_frame(ros2, graph_node):
    tf2_msgs = pytest.importorskip('tf2_msgs.msg', reason='tf2_msgs comes with make ros2-tools')
    node = graph_node
    spin = lambda dt: node.executor_.spin_once(timeout_sec=dt)  # noqa: E731
    launch = Launch(ros2, 'seed:=4', 'rate:=1.0')
    try:
        dynamic: list = []
        static: list = []
        clock: list[float] = []
        node.create_subscription(tf2_msgs.TFMessage, '/tf', lambda m: dynamic.extend(
            m.transforms), TF_QOS)
        node.create_subscription(tf2_msgs.TFMessage, '/tf_static', lambda m: static.extend(
            m.transforms), TF_STATIC_LISTENER_QOS)
        node.create_subscription(Clock, '/clock', lambda m: clock.append(
            m.clock.sec + m.clock.nanosec * 1e-9), 10)
        frames = [RoverFrames(r) for r in ROVERS]
        moving = {pair for fr in frames for pair in ((fr.odom, fr.base_link),
                                                     (fr.base_link, fr.mast_pan),
                                                     (fr.mast_pan, fr.mast_tilt))}
        wait_for(lambda: moving <= {(t.header.frame_id, t.child_frame_id) for t in dynamic}
                 or launch.proc.poll() is not None, 90.0, spin=spin,
                 what='every moving transform on /tf')
        assert launch.proc.poll() is None, launch.text()[-3000:]

        # the static chain as `ros2 topic echo` prints it (it takes the latched message)
        # the stereo nodes' fixed map -> odom (no fiducial correction): static
        wait_for(lambda: {(fr.map, fr.odom) for fr in frames}
                 <= {(t.header.frame_id, t.child_frame_id) for t in static}, 30.0, spin=spin,
                 what='map -> odom on /tf_static')
        # the simulator's message: the one with the rovers' links (the stereo nodes' hold one)
        out = subprocess.run([ros2, 'topic', 'echo', '--once', '--no-daemon', '--qos-durability',
                              'transient_local', '--qos-reliability', 'reliable',
                              '--filter', 'len(m.transforms) > 1', '/tf_static',
                              'tf2_msgs/msg/TFMessage'],
                             check=False, capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr[-2000:]
        echoed = {(t['header']['frame_id'], t['child_frame_id']): t
                  for t in yaml.safe_load(out.stdout.split('---')[0])['transforms']}
        for fr in frames:
            for pair in ((fr.base_link, fr.ft_sensor), (fr.mast_tilt, fr.optical('left')),
                         (fr.optical('left'), fr.optical('right'))):
                assert pair in echoed, (pair, sorted(echoed))
            base = echoed[(fr.optical('left'), fr.optical('right'))]['transform']['translation']
            assert base['x'] == pytest.approx(0.038) and base['y'] == base['z'] == 0.0

        # every frame any topic stamps, for a few sim seconds
        stamped: set[str] = set()
        for topic, types in node.get_topic_names_and_types():
            if types[0] in SKIP_TYPES or topic in ('/rosout', '/parameter_events'):
                continue
            node.create_subscription(get_message(types[0]), topic,
                                     lambda m: _frames_in(m, stamped),
                                     _reader_qos(node, topic))
        start = len(dynamic)
        wait_for(lambda: clock, 30.0, spin=spin, what='/clock')
        t0 = clock[-1]
        wait_for(lambda: clock[-1] >= t0 + 4.0, 60.0, spin=spin, what='4 sim s')

        parents: dict[str, set[str]] = defaultdict(set)
        for t in static + dynamic:
            parents[t.child_frame_id].add(t.header.frame_id)
        two = {c: p for c, p in parents.items() if len(p) > 1}
        assert not two, f'frames with two parents: {two}'

        def reaches_map(f: str) -> bool:
            seen = set()
            while f != 'map':
                if f in seen or f not in parents:
                    return False
                seen.add(f)
                f = next(iter(parents[f]))
            return True

        assert {'map', 'rover1/base_link', 'rover2/left_camera_optical_frame'} <= stamped
        lost = sorted(f for f in stamped if not reaches_map(f))
        assert not lost, f'stamped frames not in the tree under map: {lost}'
        assert not any(f.startswith('truth/') for f in parents), 'truth in the tree by default'

        # /tf on the sim clock, at the odometry rate (50 Hz) or faster for every rover
        for fr in frames:
            odom = sorted(t.header.stamp.sec + t.header.stamp.nanosec * 1e-9
                          for t in dynamic[start:] if t.child_frame_id == fr.base_link)
            assert odom and odom[-1] - odom[0] >= 2.0, (fr.rover, odom[:3], odom[-3:])
            assert len(odom) >= 0.95 * 50.0 * (odom[-1] - odom[0]), (fr.rover, len(odom))
            assert all(abs(s - t0) < 30.0 for s in odom), 'stamps not on the sim clock'
    finally:
        launch.close()


def test_a_simulator_whose_frames_are_taken_refuses_to_start(tmp_path):
    first = NodeProcess('rover_sim', 'sim', ['-p', 'rovers:=1', '-p', 'stereo_rate_hz:=0.0',
                                             '-p', 'frame_prefix:=site_x/'],
                        log_path=tmp_path / 'first.log')
    with first:
        wait_for(lambda: 'rovers, seed' in first.log_text(), 60.0, what='the first simulator')
        # another team's namespace but the same frame prefix: refused, with the reason
        out = subprocess.run(
            [first.cmd[0], '--ros-args', '-r', '__ns:=/team_b', '-p', 'rovers:=1',
             '-p', 'stereo_rate_hz:=0.0', '-p', 'frame_prefix:=site_x/',
             '-p', 'frame_check_s:=5.0'],
            check=False, capture_output=True, text=True, timeout=60)
        said = out.stdout + out.stderr
        assert out.returncode == 1, said[-3000:]
        assert 'site_x/rover1/' in said and 'frame_prefix' in said, said[-3000:]
