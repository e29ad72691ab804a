"""`coop_bringup.graph`: a launch file run by launch's LaunchService in a child process, with
its processes reported to the client (which run, which ended, stopping one), and every process
gone after the graph's exit; and the settings a client reads from the parameter file."""
from __future__ import annotations

import os
import time

import pytest
from coop_bringup.graph import GraphError, LaunchedGraph, node_logs, node_settings

from coop_common.testing import ros2_tools, wait_for

LAUNCH = """
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.substitutions import LaunchConfiguration


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument('code', default_value='0'),
        ExecuteProcess(cmd=['sleep', '60'], name='sleeper', output={'both': {'own_log'}}),
        # launch ends once nothing it started runs: this one keeps it up past the sleeper
        ExecuteProcess(cmd=['sleep', '60'], name='keeper', output={'both': {'own_log'}}),
        ExecuteProcess(cmd=['sh', '-c', ['echo said; exit ', LaunchConfiguration('code')]],
                       name='quitter', output={'both': {'own_log'}}),
    ])
"""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f'/proc/{pid}/stat') as f:     # a zombie awaiting its parent counts as gone
        return f.read().split(')')[-1].split()[0] != 'Z'


def test_the_client_sees_each_process_stops_one_and_leaves_none(tmp_path):
    ros2_tools()
    file = tmp_path / 'two.launch.py'
    file.write_text(LAUNCH)
    with LaunchedGraph(file, {'code': '3'}, log_dir=tmp_path / 'logs') as graph:
        graph.wait_started(['sleeper', 'quitter'], timeout_s=30)
        # the one that exited by itself is dead, with its exit code; the other runs
        wait_for(lambda: 'quitter' in graph.dead(), 10.0, what='the quitter reported')
        assert graph.processes()['quitter']['returncode'] == 3
        pid = graph.pid('sleeper')
        assert pid is not None and _alive(pid)
        assert graph.dead() == ['quitter'] and graph.running()
        # a process stopped by the client is not dead, and launch carries on
        graph.stop('sleeper')
        assert graph.processes()['sleeper']['returncode'] is not None
        assert graph.dead() == ['quitter'] and graph.running()
    assert not _alive(pid) and not graph.running()
    logs = node_logs(tmp_path / 'logs')
    assert 'said' in logs['quitter'].read_text()


def test_every_process_is_gone_after_exit_and_a_bad_file_is_told(tmp_path):
    ros2_tools()
    file = tmp_path / 'two.launch.py'
    file.write_text(LAUNCH)
    with LaunchedGraph(file, {}, log_dir=tmp_path / 'a') as graph:
        graph.wait_started(['sleeper'], timeout_s=30)
        pid = graph.pid('sleeper')
    deadline = time.monotonic() + 5
    while _alive(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(pid)
    broken = tmp_path / 'broken.launch.py'
    broken.write_text('raise ValueError("no such scenario")\n')
    with LaunchedGraph(broken, {}, log_dir=tmp_path / 'b') as graph, \
            pytest.raises(GraphError, match='launch ended'):
        graph.wait_started(['anything'], timeout_s=30)
    with pytest.raises(GraphError, match='no launch file'):
        LaunchedGraph(tmp_path / 'missing.launch.py', {}, log_dir=tmp_path / 'c')


def test_node_settings_come_from_the_one_parameter_file(tmp_path):
    assert node_settings('view_planner')['camera_height_m'] == 0.78
    assert node_settings('nobody') == {}
    bad = tmp_path / 'bad.yaml'
    bad.write_text('/**/x: [')
    with pytest.raises(GraphError, match=r'bad\.yaml'):
        node_settings('x', bad)
