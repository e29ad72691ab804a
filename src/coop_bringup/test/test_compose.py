"""`coop_bringup compose`: several nodes in one process and executor, each with its own
parameters from a file keyed by node; one that cannot start, or whose callback raises, stops
the process with its name."""
from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest
from coop_bringup.compose import ComposeError, node_class


def test_a_spec_names_the_node_class_of_the_executable():
    from coop_insertion.master_node import MasterNode
    from coop_mapping.mapper_node import MapperNode
    assert node_class('coop_insertion/master') is MasterNode
    assert node_class('coop_mapping/mapper') is MapperNode
    for bad, why in (('coop_mapping', 'expected <package>/<executable>'),
                     ('coop_mapping/nothing', "has no executable 'nothing'"),
                     ('no_such_package/mapper', "package 'no_such_package'"),
                     ('coop_bringup/table_5_1', 'is not a node executable'),
                     ('coop_bringup/mission', 'is not a node executable')):
        with pytest.raises(ComposeError, match=why):
            node_class(bad)


@pytest.mark.graph
def test_two_nodes_in_one_process_take_their_own_parameters(tmp_path):
    from rclpy.parameter_client import AsyncParameterClient

    from coop_common.testing import NodeProcess, Probe
    params = tmp_path / 'composed.yaml'
    params.write_text(textwrap.dedent("""\
        /**/mapper:
          ros__parameters:
            publish_period_s: 2.5
        /**/view_planner:
          ros__parameters:
            camera_height_m: 0.7
        """))
    with NodeProcess('coop_bringup', 'compose', ['--params-file', str(params)],
                     args=['coop_mapping/mapper', 'coop_viewplan/view_planner'],
                     log_path=tmp_path / 'compose.log') as proc, Probe() as probe:
        probe.spin_until(lambda: {'mapper', 'view_planner'}
                         <= set(probe.node.get_node_names()), 60, 'both nodes',
                         procs=[proc])
        got = {}
        for node, name in (('mapper', 'publish_period_s'), ('view_planner', 'camera_height_m'),
                           ('mapper', 'max_points')):
            client = AsyncParameterClient(probe.node, node)
            probe.spin_until(lambda c=client: c.services_are_ready(), 30, f'{node} params')
            fut = client.get_parameters([name])
            probe.spin_until(fut.done, 30, f"{node}'s {name}")
            got[node, name] = fut.result().values[0]
        assert got['mapper', 'publish_period_s'].double_value == 2.5
        assert got['view_planner', 'camera_height_m'].double_value == 0.7
        assert got['mapper', 'max_points'].integer_value == 1_000_000     # its default
        assert proc.alive()


@pytest.mark.graph
def test_a_node_that_cannot_start_stops_the_process_with_its_name(tmp_path):
    from coop_common.testing import NodeProcess, wait_for
    params = tmp_path / 'bad.yaml'
    params.write_text('/**/mapper:\n  ros__parameters:\n    resolution_m: -1.0\n')
    with NodeProcess('coop_bringup', 'compose', ['--params-file', str(params)],
                     args=['coop_viewplan/view_planner', 'coop_mapping/mapper'],
                     log_path=tmp_path / 'compose.log') as proc:
        wait_for(lambda: not proc.alive(), 60, what='the process to stop')
        assert proc.proc.returncode == 1
        assert 'cannot start coop_mapping/mapper' in proc.log_text()
        assert 'resolution_m' in proc.log_text()


def test_a_node_whose_callback_raises_stops_the_process_with_its_name():
    # two plain nodes through run_nodes, in a process of their own (it installs the signal
    # handlers and owns rclpy's default context)
    code = textwrap.dedent("""
        import sys
        from rclpy.node import Node
        from coop_common.node_util import NodeFailed, run_nodes

        class Quiet(Node):
            def __init__(self):
                super().__init__('quiet')

        class Faulty(Node):
            def __init__(self):
                super().__init__('faulty')
                self.create_timer(0.01, self.tick)

            def tick(self):
                raise ZeroDivisionError('a callback fell over')

        try:
            run_nodes([Quiet, Faulty])
        except NodeFailed as exc:
            print('stopped by', exc.node, '|', exc)
            sys.exit(1)
        sys.exit(0)
    """)
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         timeout=60, check=False)
    assert out.returncode == 1, out.stderr
    assert 'stopped by /faulty | /faulty: ZeroDivisionError: a callback fell over' in out.stdout
    assert 'stops the process' in out.stderr
