r"""The whole mission graph (thesis ch. 5.1, Fig. 4-2): the data source, each rover's
identifier and stereo node, the team's mapper and view planner, the insertion's master and
slave, and optionally the recorder and the live view, all on sim time.

    ros2 launch coop_bringup mission.launch.py                         # sim, 2 rovers
    ros2 launch coop_bringup mission.launch.py team:=team_a live_view:=true
    ros2 launch coop_bringup mission.launch.py source:=bag bag:=bags/mapping_two_rovers \\
        insertion:=false
    ros2 launch coop_bringup mission.launch.py source:=hw \\
        hw_ports:='rover1=/dev/ttyUSB0 rover2=/dev/ttyUSB1'

The graph does nothing by itself: a client drives it (`ros2 run coop_bringup mission`, which
starts this very file through launch's Python API and runs the phases against it; the
insertion rig `coop_bringup.rig` and `table_5_1` do the same). Every node's settings are in
`config/mission.yaml` (keyed /**/<node>, so they apply under any team and rover namespace);
the arguments below are the scenario's and the run's, not the nodes'. Every name is relative,
so `team` moves the whole team.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import yaml
from ament_index_python.packages import get_package_share_directory
from launch import LaunchContext, LaunchDescription
from launch.actions import (
    DeclareLaunchArgument,
    EmitEvent,
    GroupAction,
    OpaqueFunction,
    RegisterEventHandler,
)
from launch.events import matches_action
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import LifecycleNode, Node, PushRosNamespace
from launch_ros.event_handlers import OnStateTransition
from launch_ros.events.lifecycle import ChangeState
from lifecycle_msgs.msg import Transition

INCH = 0.0254
SOURCES = ('sim', 'bag', 'hw')
#: lockstep's tick and ack topics (coop_common.lockstep_node), relative to the team
LOCKSTEP_TOPICS = ('sim/lockstep/tick', 'sim/lockstep/ack')
#: the nodes that one `coop_bringup compose` process runs with composed:=true
COMPOSABLE = {'master': 'coop_insertion/master', 'slave': 'coop_insertion/slave',
              'mapper': 'coop_mapping/mapper', 'view_planner': 'coop_viewplan/view_planner'}

ARGUMENTS = (
    ('team', '', 'namespace of the whole team (empty: the root)'),
    ('source', 'sim', "the rovers' data: the simulator, a recorded bag or the hardware "
                      'bridges (rover_hw)'),
    ('bag', '', 'the bag to play with source:=bag'),
    ('hw_ports', '', "source:=hw: each rover's controller port, 'rover1=/dev/ttyUSB0 "
                     "rover2=...'"),
    ('rovers', '2', 'how many rovers (rover1 .. roverN; rover1 is the master, rover2 the '
                    "slave), or their names, space separated (the simulator's: rover1 .. N)"),
    ('stereo_rovers', '', 'the rovers whose stereo pairs the simulator renders and, with '
                          'mapping, ranges into the map (space separated; empty: every rover)'),
    ('identify', 'true', "each rover's base identifier (coop_id identifier)"),
    ('driving', 'true', "each rover's driver (coop_insertion driver: its drive_to_pose action; "
                        'sim and hw sources)'),
    ('mapping', 'true', "the team's map: the stereo nodes, the mapper and the view planner"),
    ('map_input', 'clouds', "what each rover's stereo node sends the mapper: its clouds, or "
                            "map contributions made from them (what a rover's radio link can "
                            'carry: coop_mapping README, Contributions)'),
    ('insertion', 'true', "the insertion's master (rover1) and slave (rover2)"),
    ('arm_feedforward', 'off', "each rover's arm_feedforward (coop_insertion: the base's motion "
                               'fed into the arm servo, Eq. A-4) on the identified, nominal or '
                               'no base model (identified, nominal, none), or off; sim source '
                               'only, and not a lockstep participant'),
    ('seed', '1', "the simulator's seed (site clutter, sensor noise) and the master's"),
    ('occlusion_density', '', "the simulator's obstacles' footprint fraction of the site "
                              "(empty: the simulator's default)"),
    ('slot_in', '4.5', "the slot's width (in; Table 5-1: 5.0, 4.5, 4.375)"),
    ('world', '', "the simulator's world file (empty: with insertion:=true coop_insertion's "
                  "insertion site, else the simulator's default)"),
    ('site_map', '', 'a saved map the mapper starts from (empty: none)'),
    ('cg_to_arm', '', "the slave's arm mount r_2 (m, '[x, y, z]'; empty: the slave's "
                      'nominal)'),
    ('image_width', '', "the simulator's stereo images (empty: with insertion:=true 640 x "
                        "480, which the 0.25 in slot markers need, else the simulator's "
                        'default)'),
    ('image_height', '', "the simulator's stereo images (empty: as for image_width)"),
    ('stereo_rate_hz', '', "the simulator's stereo frame rate (Hz; empty: its default)"),
    ('render_workers', '', "the simulator's processes drawing right eyes (0: none; empty: "
                           'its default)'),
    ('rate', '1.0', 'sim or playback speed (sim: 0 = as fast as it can)'),
    ('lockstep', 'false', 'the simulator steps no round before every participant answered '
                          'the last (outcomes that do not depend on load)'),
    ('lockstep_period_s', '0.01', 'sim time of one lockstep round (s)'),
    ('clients', '', 'lockstep participants besides the nodes (the clients that drive the '
                    "graph, e.g. 'mission'), space separated"),
    ('composed', 'false', 'the master, the slave, the mapper and the view planner in one '
                          'process (coop_bringup compose)'),
    ('record', '', 'record the run into this directory (rover_bag record; empty: no bag)'),
    ('record_all', 'false', 'record the bulk streams too (images, clouds, map snapshots)'),
    ('live_view', 'false', 'serve the live view (Foxglove WebSocket)'),
    ('live_port', '8765', "the live view's port"),
    ('overrides', '', 'a parameter file over params_file and the arguments (keyed '
                      '/**/<node>; tests and experiments: empty, none)'),
    ('clock', 'global', "the time source's topic: /clock, or the team's own <team>/clock (two "
                        'simulated teams in one domain)'),
    ('output', 'screen', "where the nodes' output goes: screen, log (launch's log), own_log (a "
                         "file per process in launch's log directory) or both"),
)
#: what the recorder leaves out: ROS's own chatter and the lockstep rounds' tick and acks (a
#: fifth of a lockstep mission's messages, which a replay has no use for) always, the bulk
#: streams unless
#: record_all:=true, each MBs a second (a short mission's 10 sim s held 183 + 162 MB of stereo
#: clouds, 119 MB of map snapshots, 51 MB of map updates, 19 MB of map clouds; everything
#: else, 6 MB). The final map is the mapper's file; /map/grid (the 2-D map) stays, as do
#: sensors, poses and estimates.
BAG_NEVER = ('/rosout', '/parameter_events', *(f'*/{t}' for t in LOCKSTEP_TOPICS))
BAG_BULK = ('*/image_raw', '*/stereo/points', '/map/voxels', '/map/updates', '/map/surface',
            '/map/occupied')


def _flag(text: str, name: str) -> bool:
    if text.lower() not in ('true', 'false'):
        raise ValueError(f'{name}:={text!r}: give true or false')
    return text.lower() == 'true'


def _ports(text: str, rovers: list[str]) -> dict[str, str]:
    ports = dict(p.split('=', 1) for p in text.split() if '=' in p)
    missing = [r for r in rovers if r not in ports]
    if missing or len(ports) != len(text.split()):
        raise ValueError(f"hw_ports:={text!r}: give 'rover=port' for each of {rovers}")
    return ports


def _rovers(text: str, source: str) -> list[str]:
    """The rovers' names from a count or the names themselves."""
    names = text.replace(',', ' ').split()
    if len(names) == 1 and names[0].isdigit():
        names = [f'rover{i + 1}' for i in range(int(names[0]))]
    if not names or len(set(names)) != len(names):
        raise ValueError(f'rovers:={text!r}: give a count or distinct rover names, e.g. '
                         '"rover1 rover2"')
    expected = [f'rover{i + 1}' for i in range(len(names))]
    if source == 'sim' and names != expected:
        raise ValueError(f'rovers:={text!r}: the simulator names its rovers {expected}')
    return names


def _graph(context: LaunchContext) -> list:
    a = {name: LaunchConfiguration(name).perform(context) for name, *_ in ARGUMENTS}
    params_file = LaunchConfiguration('params_file').perform(context)
    overrides = [a['overrides']] if a['overrides'] else []
    if a['source'] not in SOURCES:
        raise ValueError(f'source:={a["source"]!r} is not one of {list(SOURCES)}')
    rovers = _rovers(a['rovers'], a['source'])
    n = len(rovers)
    stereo_rovers = a['stereo_rovers'].split() or rovers
    if set(stereo_rovers) - set(rovers):
        raise ValueError(f'stereo_rovers:={a["stereo_rovers"]!r}: not among {rovers}')
    identify, mapping, insertion = (_flag(a[k], k) for k in ('identify', 'mapping',
                                                              'insertion'))
    driving = _flag(a['driving'], 'driving') and a['source'] != 'bag'
    if a['map_input'] not in ('clouds', 'contributions'):
        raise ValueError(f'map_input:={a["map_input"]!r}: give clouds or contributions')
    contribute = a['map_input'] == 'contributions'
    if a['arm_feedforward'] not in ('off', 'identified', 'nominal', 'none'):
        raise ValueError(f'arm_feedforward:={a["arm_feedforward"]!r}: give identified, nominal, '
                         'none or off')
    if a['arm_feedforward'] != 'off' and a['source'] != 'sim':
        raise ValueError('arm_feedforward: the efforts go to the simulator: source:=sim only')
    lockstep, composed = _flag(a['lockstep'], 'lockstep'), _flag(a['composed'], 'composed')
    if insertion and n < 2:
        raise ValueError('insertion:=true needs a master and a slave: rovers:=2 or more')
    if lockstep and a['source'] != 'sim':
        raise ValueError('lockstep:=true steps the simulator: source:=sim only')
    team_ns = '/' + a['team'].strip('/') if a['team'].strip('/') else ''
    if a['clock'] not in ('global', 'team'):
        raise ValueError(f'clock:={a["clock"]!r}: give global or team')
    if a['output'] not in ('screen', 'log', 'own_log', 'both'):
        raise ValueError(f'output:={a["output"]!r}: give screen, log, own_log or both')
    # own_log: one file per process, <process>.log (launch's own_log alone also writes its
    # -stdout and -stderr files)
    output = {'both': {'own_log'}} if a['output'] == 'own_log' else a['output']
    # /clock is the one global name: two simulated teams in one domain each keep their own,
    # <team>/clock for every node of the team (a relative 'clock' would resolve in a rover's
    # namespace for the rover's nodes, where no clock ticks)
    clock = [('/clock', f'{team_ns}/clock')] if a['clock'] == 'team' else []
    # frames follow the team as names do (team_a/map, team_a/rover1/base_link: two teams'
    # trees share no frame); a bag's frames are what it recorded
    sim_time = {'use_sim_time': a['source'] != 'hw',
                'frame_prefix': f'{team_ns[1:]}/' if team_ns and a['source'] == 'sim' else ''}
    # a rover's own node answers the simulator's lockstep at the team's level
    to_team = [(t, f'{team_ns}/{t}') for t in LOCKSTEP_TOPICS] if lockstep else []
    participants: list[str] = []
    nodes: list = []

    def node(name: str, package: str, executable: str, params: dict, *, ns: str = '',
             participant: bool = False, remaps: list | None = None, lifecycle: bool = False,
             arguments: list | None = None):
        """One node of the graph: the params file, then the run's values."""
        if participant and lockstep:
            params = {**params, 'lockstep': True}
            participants.append(f'{ns}/{name}' if ns else name)
        kind = LifecycleNode if lifecycle else Node
        made = kind(package=package, executable=executable, name=name, namespace=ns,
                    output=output, arguments=arguments or [],
                    parameters=[params_file, sim_time, params, *overrides],
                    remappings=(remaps or []) + clock
                    + (to_team if ns and participant else []))
        nodes.append(made)
        return made

    # the data source (the simulator is made last: its lockstep participants are the graph's)
    if a['source'] == 'sim':
        sim = {'rovers': n, 'seed': int(a['seed']), 'stereo_rovers': stereo_rovers,
               'real_time_factor': float(a['rate'])}
        if insertion:
            sim |= {'slot_gap_m': float(a['slot_in']) * INCH, 'image_width': 640,
                    'image_height': 480,
                    'world_yaml': str(Path(get_package_share_directory('coop_insertion'))
                                      / 'config' / 'insertion_world.yaml')}
        given = {'occlusion_density': float, 'image_width': int, 'image_height': int,
                 'stereo_rate_hz': float, 'render_workers': int, 'world': str}
        sim |= {('world_yaml' if k == 'world' else k): kind(a[k])
                for k, kind in given.items() if a[k]}
    elif a['source'] == 'bag':
        if not a['bag']:
            raise ValueError('source:=bag needs bag:=<path of a recorded bag>')
        nodes.append(Node(package='rover_bag', executable='play', name='rover_bag_player',
                          namespace='', output=output, remappings=clock,
                          arguments=[str(Path(a['bag']).resolve())],
                          parameters=[params_file, {'rate': float(a['rate'])}, *overrides]))
    else:
        for r, port in _ports(a['hw_ports'], rovers).items():
            bridge = node('bridge', 'rover_hw', 'bridge', {'port': port}, ns=r, lifecycle=True)
            nodes += _bring_up(bridge)
    # each rover's own nodes
    for r in rovers:
        if identify:
            node('identifier', 'coop_id', 'identifier', {}, ns=r, participant=True)
        if driving:       # its obstacles from the team's 2-D map, above the rovers' namespaces
            node('driver', 'coop_insertion', 'driver', {}, ns=r, participant=True,
                 remaps=[('map/grid', f'{team_ns}/map/grid')])
        if mapping and r in stereo_rovers:
            node('stereo', 'coop_mapping', 'stereo', {'contribute': contribute}, ns=r)
        if a['arm_feedforward'] != 'off':
            node('arm_feedforward', 'coop_insertion', 'arm_feedforward',
                 {'source': a['arm_feedforward']}, ns=r)
    # the team's nodes (master and slave: participants of lockstep)
    team: dict[str, tuple[str, str, dict]] = {}
    if mapping:
        team['mapper'] = ('coop_mapping', 'mapper', {
            'rovers': stereo_rovers, 'map_input': a['map_input'],
            **({'map_file': a['site_map']} if a['site_map'] else {})})
        team['view_planner'] = ('coop_viewplan', 'view_planner', {})
    if insertion:
        slot = {'slot_width_m': float(a['slot_in']) * INCH}
        team['master'] = ('coop_insertion', 'master', {**slot, 'seed': int(a['seed'])})
        team['slave'] = ('coop_insertion', 'slave', {
            **slot, **({'cg_to_arm': [float(v) for v in yaml.safe_load(a['cg_to_arm'])]}
                       if a['cg_to_arm'] else {})})
    together = [k for k in team if composed and k in COMPOSABLE]
    for name, (pkg, exe, params) in team.items():
        if name not in together:
            node(name, pkg, exe, params, participant=name in ('master', 'slave'))
    if together:
        # one process: each node's values keyed by its name, as ROS's per-node parameters
        per_node = {}
        for name in together:
            own = {**team[name][2], **sim_time}
            if lockstep and name in ('master', 'slave'):
                own['lockstep'] = True
                participants.append(name)
            per_node[f'/**/{name}'] = {'ros__parameters': own}
        values = Path(tempfile.mkdtemp(prefix='compose_')) / 'composed.yaml'
        values.write_text(yaml.safe_dump(per_node))
        nodes.append(Node(package='coop_bringup', executable='compose', output=output,
                          arguments=[COMPOSABLE[k] for k in together], remappings=clock,
                          parameters=[params_file, str(values), *overrides]))
    if a['record']:
        exclude = BAG_NEVER + (() if _flag(a['record_all'], 'record_all') else BAG_BULK)
        node('record', 'rover_bag', 'record', {
            'output': str(Path(a['record']).resolve()), 'exclude': list(exclude)})
    if _flag(a['live_view'], 'live_view'):
        node('live_view', 'coop_bringup', 'live_view', {'port': int(a['live_port']),
                                                        'rovers': rovers})
    if a['source'] == 'sim':
        if lockstep:
            sim |= {'lockstep_participants': participants + a['clients'].split(),
                    'lockstep_period_s': float(a['lockstep_period_s'])}
        sim['frame_prefix'] = sim_time['frame_prefix']
        nodes.insert(0, Node(package='rover_sim', executable='sim', name='rover_sim', namespace='',
                             output=output, remappings=clock,
                             parameters=[params_file, sim, *overrides]))
    graph = nodes
    return [GroupAction([PushRosNamespace(a['team']), *graph]) if a['team']
            else GroupAction(graph)]


def _bring_up(bridge: LifecycleNode) -> list:
    """A hardware bridge configured when it starts and activated once configured."""
    def change(transition: int) -> EmitEvent:
        return EmitEvent(event=ChangeState(lifecycle_node_matcher=matches_action(bridge),
                                           transition_id=transition))
    return [change(Transition.TRANSITION_CONFIGURE),
            RegisterEventHandler(OnStateTransition(
                target_lifecycle_node=bridge, goal_state='inactive',
                entities=[change(Transition.TRANSITION_ACTIVATE)]))]


def generate_launch_description() -> LaunchDescription:
    """The arguments, then the graph they describe (made when launch runs it)."""
    config = Path(get_package_share_directory('coop_bringup')) / 'config' / 'mission.yaml'
    return LaunchDescription([
        *(DeclareLaunchArgument(name, default_value=default, description=text)
          for name, default, text in ARGUMENTS),
        DeclareLaunchArgument('params_file', default_value=str(config),
                              description='parameters of every node (keyed /**/<node>)'),
        OpaqueFunction(function=_graph),
    ])
