"""One team of cooperative rovers: the data source, each rover's identifier and stereo node
under its namespace, and the team's mapper and view planner, all on sim time.

    ros2 launch coop_bringup team.launch.py                          # sim, rover1 + rover2
    ros2 launch coop_bringup team.launch.py team:=team_a seed:=3     # the same under /team_a
    ros2 launch coop_bringup team.launch.py source:=bag bag:=bags/mapping_two_rovers

Every name is relative, so `team` moves the whole team; parameters come from
`config/team.yaml` (keyed /**/<node>, so they apply under any namespace) or `params_file`.
"""
from __future__ import annotations

from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, GroupAction, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node, PushRosNamespace

SOURCES = ('sim', 'bag')


def _rovers(text: str) -> list[str]:
    names = [r for r in text.replace(',', ' ').split() if r]
    if not names or len(set(names)) != len(names):
        raise ValueError(f'rovers:={text!r}: give distinct rover names, e.g. "rover1 rover2"')
    return names


def _team(context: LaunchContext) -> list:
    arg = {name: LaunchConfiguration(name).perform(context) for name in (
        'team', 'source', 'bag', 'rovers', 'params_file', 'seed', 'rate', 'identify', 'clock')}
    if arg['source'] not in SOURCES:
        raise ValueError(f'source:={arg["source"]!r} is not one of {list(SOURCES)}')
    rovers = _rovers(arg['rovers'])
    params = arg['params_file']
    # /clock is the one global name: two simulated teams in one domain each keep their own,
    # <team>/clock for every node of the team (a relative 'clock' would resolve in a rover's
    # namespace for the rover's nodes, where no clock ticks)
    team_ns = '/' + arg['team'].strip('/') if arg['team'].strip('/') else ''
    remap = [('/clock', f'{team_ns}/clock')] if arg['clock'] == 'team' else []
    # frames follow the team as names do (team_a/map, team_a/rover1/base_link: two teams' trees
    # share no frame); a bag's frames are what it recorded
    frames = {'frame_prefix': f'{team_ns[1:]}/' if team_ns and arg['source'] == 'sim' else ''}
    sim_time = {'use_sim_time': True}
    if arg['source'] == 'sim':
        source = Node(package='rover_sim', executable='sim', name='rover_sim', output='screen',
                      remappings=remap,
                      parameters=[params, frames, {'rovers': len(rovers),
                                                   'seed': int(arg['seed']),
                                                   'real_time_factor': float(arg['rate'])}])
        expected = [f'rover{i + 1}' for i in range(len(rovers))]
        if rovers != expected:
            raise ValueError(f'rovers:={arg["rovers"]!r}: the simulator names its rovers '
                             f'{expected}')
    else:
        if not arg['bag']:
            raise ValueError('source:=bag needs bag:=<path of a recorded bag>')
        source = Node(package='rover_bag', executable='play', name='rover_bag_player',
                      output='screen', arguments=[str(Path(arg['bag']).resolve())],
                      remappings=remap,
                      parameters=[{'rate': float(arg['rate'])}])
    per_rover = []
    for r in rovers:
        nodes = [Node(package='coop_mapping', executable='stereo', name='stereo',
                      output='screen', remappings=remap, parameters=[params, sim_time, frames])]
        if arg['identify'].lower() == 'true':
            nodes.append(Node(package='coop_id', executable='identifier', name='identifier',
                              output='screen', remappings=remap,
                              parameters=[params, sim_time, frames]))
        per_rover.append(GroupAction([PushRosNamespace(r), *nodes]))
    team = [
        source,
        *per_rover,
        Node(package='coop_mapping', executable='mapper', name='mapper', output='screen',
             remappings=remap, parameters=[params, sim_time, frames, {'rovers': rovers}]),
        Node(package='coop_viewplan', executable='view_planner', name='view_planner',
             output='screen', remappings=remap, parameters=[params, sim_time, frames]),
    ]
    return [GroupAction([PushRosNamespace(arg['team']), *team]) if arg['team']
            else GroupAction(team)]


def generate_launch_description() -> LaunchDescription:
    """One team's nodes (the simulator or a bag, stereo, identifier, mapper, view planner)."""
    config = Path(get_package_share_directory('coop_bringup')) / 'config' / 'team.yaml'
    return LaunchDescription([
        DeclareLaunchArgument('team', default_value='',
                              description='namespace of the whole team (empty: the root)'),
        DeclareLaunchArgument('source', default_value='sim', choices=list(SOURCES),
                              description='where the sensor data come from'),
        DeclareLaunchArgument('bag', default_value='',
                              description='the bag to play with source:=bag'),
        DeclareLaunchArgument('rovers', default_value='rover1 rover2',
                              description='the rovers (namespaces), space or comma separated'),
        DeclareLaunchArgument('params_file', default_value=str(config),
                              description='parameters of every node (keyed /**/<node>)'),
        DeclareLaunchArgument('seed', default_value='1', description="the simulator's seed"),
        DeclareLaunchArgument('rate', default_value='1.0',
                              description='sim or playback speed (sim: 0 = as fast as it can)'),
        DeclareLaunchArgument('identify', default_value='true', choices=['true', 'false'],
                              description="start each rover's identifier"),
        DeclareLaunchArgument('clock', default_value='global', choices=['global', 'team'],
                              description="the time source's topic: /clock, or the team's own "
                              '<team>/clock (two simulated teams in one domain)'),
        OpaqueFunction(function=_team),
    ])
