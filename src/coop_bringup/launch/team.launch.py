"""One team of cooperative rovers mapping their site: the data source, each rover's identifier
and stereo node under its namespace, and the team's mapper and view planner, all on sim time.
It is mission.launch.py without the insertion's master and slave (the same nodes, settings
and arguments; `ros2 launch coop_bringup mission.launch.py --show-args` lists them all).

    ros2 launch coop_bringup team.launch.py                          # sim, rover1 + rover2
    ros2 launch coop_bringup team.launch.py team:=team_a seed:=3     # the same under /team_a
    ros2 launch coop_bringup team.launch.py source:=bag bag:=bags/mapping_two_rovers

Every name is relative, so `team` moves the whole team; parameters come from
`config/mission.yaml` (keyed /**/<node>, so they apply under any namespace) or `params_file`.
"""
from __future__ import annotations

from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, IncludeLaunchDescription
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch.substitutions import LaunchConfiguration

#: the arguments this file passes on (their meaning: mission.launch.py's)
PASSED = (('team', ''), ('bag', ''), ('rovers', 'rover1 rover2'),
          ('seed', '1'), ('rate', '1.0'), ('identify', 'true'), ('clock', 'global'))


def generate_launch_description() -> LaunchDescription:
    """mission.launch.py without the insertion (its arguments passed on)."""
    share = Path(get_package_share_directory('coop_bringup'))
    return LaunchDescription([
        *(DeclareLaunchArgument(name, default_value=default,
                                description="as mission.launch.py's")
          for name, default in PASSED),
        DeclareLaunchArgument('source', default_value='sim', choices=['sim', 'bag', 'hw'],
                              description="as mission.launch.py's"),
        DeclareLaunchArgument('params_file', default_value=str(share / 'config' /
                                                               'mission.yaml'),
                              description='parameters of every node (keyed /**/<node>)'),
        IncludeLaunchDescription(
            PythonLaunchDescriptionSource(str(share / 'launch' / 'mission.launch.py')),
            launch_arguments=[*((name, LaunchConfiguration(name))
                                for name in ('source', *(n for n, _ in PASSED))),
                              ('params_file', LaunchConfiguration('params_file')),
                              ('insertion', 'false')]),
    ])
