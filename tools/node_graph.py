#!/usr/bin/env python3
"""Draw the node graph from the running graph: start the mission's graph (coop_bringup's
mission.launch.py: the simulator, each rover's stereo node, identifier and driver, the mapper,
the view planner, the master and the slave), ask the ROS graph for every node's publishers,
subscriptions, services and action servers, and write a Mermaid flowchart to
docs/node-graph.md (GitHub renders it).

Usage: python tools/node_graph.py [--out docs/node-graph.md]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

import rclpy
from coop_bringup.graph import LaunchedGraph, mission_launch_file
from rclpy.action import get_action_server_names_and_types_by_node
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from coop_common.files import write_text_atomic
from coop_common.testing import isolate_ros_environment, wait_for

ROOT = Path(__file__).resolve().parents[1]
ROVERS = ('rover1', 'rover2')
#: plumbing every node has, and the simulator's ground truth (for tests), left out of the picture
HIDDEN = ('/rosout', '/parameter_events', '/clock')
HIDDEN_SUFFIXES = ('/describe_parameters', '/get_parameters', '/get_parameter_types',
                   '/list_parameters', '/set_parameters', '/set_parameters_atomically',
                   '/get_type_description')


def _shown(name: str) -> bool:
    return (name not in HIDDEN and not name.endswith(HIDDEN_SUFFIXES)
            and not name.startswith('/sim/') and '/_action/' not in name)


def introspect(node: Node) -> dict[str, dict[str, list[str]]]:
    """Per node (full name): its shown publishers, subscriptions, services, action servers."""
    out = {}
    for name, ns in node.get_node_names_and_namespaces():
        if name == node.get_name():
            continue
        full = f'{ns.rstrip("/")}/{name}'
        out[full] = {
            'pub': sorted(t for t, _ in node.get_publisher_names_and_types_by_node(name, ns)
                          if _shown(t)),
            'sub': sorted(t for t, _ in node.get_subscriber_names_and_types_by_node(name, ns)
                          if _shown(t)),
            'srv': sorted(s for s, _ in node.get_service_names_and_types_by_node(name, ns)
                          if _shown(s)),
            'act': sorted(a for a, _ in get_action_server_names_and_types_by_node(node, name, ns)),
        }
    return out


def mermaid(graph: dict[str, dict[str, list[str]]]) -> str:
    """A flowchart: nodes grouped by namespace, a topic an edge from each publisher to each
    subscriber (or to an output box when nothing in the graph subscribes), services and actions
    listed in their server's box."""
    ids = {n: f'n{i}' for i, n in enumerate(sorted(graph))}
    groups: dict[str, list[str]] = defaultdict(list)
    for n in sorted(graph):
        groups[n.rsplit('/', 1)[0] or '/'].append(n)
    lines = ['flowchart LR']
    for ns, members in sorted(groups.items()):
        lines.append(f'  subgraph {ns.strip("/") or "team"}["{ns}"]')
        for n in members:
            # a name's last two segments, relative ('/insert' of a node at the root: 'insert')
            srv = ['/'.join(s.rsplit('/', 2)[-2:]).lstrip('/') for s in graph[n]['srv']]
            act = ['/'.join(a.rsplit('/', 2)[-2:]).lstrip('/') for a in graph[n]['act']]
            extra = ''.join(f'<br/><small>srv {s}</small>' for s in srv)
            extra += ''.join(f'<br/><small>action {a}</small>' for a in act)
            lines.append(f'    {ids[n]}["<b>{n.rsplit("/", 1)[-1]}</b>{extra}"]')
        lines.append('  end')
    subscribers: dict[str, list[str]] = defaultdict(list)
    for n, io in graph.items():
        for t in io['sub']:
            subscribers[t].append(n)
    outputs = 0
    for n in sorted(graph):
        for t in graph[n]['pub']:
            if subscribers.get(t):
                for s in sorted(subscribers[t]):
                    lines.append(f'  {ids[n]} -- "{t.lstrip("/")}" --> {ids[s]}')
            else:
                lines.append(f'  {ids[n]} -- "{t.lstrip("/")}" --> o{outputs}(( ))')
                outputs += 1
    for t in sorted(subscribers):
        if not any(t in io['pub'] for io in graph.values()):
            for s in subscribers[t]:
                lines.append(f'  i_{s.replace("/", "_")}_{t.replace("/", "_")}'
                             f'[/"{t.lstrip("/")}"/] --> {ids[s]}')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    """Start one team, read its graph and write the flowchart (`--out`)."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--out', type=Path, default=ROOT / 'docs' / 'node-graph.md')
    args = ap.parse_args(argv)
    domain = isolate_ros_environment()
    with tempfile.TemporaryDirectory(prefix='node_graph_') as logs, \
            LaunchedGraph(mission_launch_file(), {'output': 'own_log'}, log_dir=Path(logs)):
        ctx = Context()
        rclpy.init(context=ctx, domain_id=domain)
        node = Node('node_graph', context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        want = {'/rover_sim', '/mapper', '/view_planner', '/master', '/slave',
                *(f'/{r}/{n}' for r in ROVERS for n in ('stereo', 'identifier', 'driver'))}
        spin = lambda dt: ex.spin_once(timeout_sec=dt)  # noqa: E731
        wait_for(lambda: want <= set(introspect(node)), 90.0, spin=spin, what='the team')
        # every node has declared its interfaces once the mapper subscribes the clouds
        wait_for(lambda: all(introspect(node)[n]['sub'] or n == '/rover_sim' for n in want),
                 30.0, spin=spin, what="every node's subscriptions")
        graph = introspect(node)
        ex.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
    text = ('# The node graph\n\nOne team as `ros2 launch coop_bringup mission.launch.py` brings '
            'it up, drawn from the running graph by `python tools/node_graph.py` (topics as edges '
            'from publisher to subscriber; an open circle: a topic nothing in the team '
            'subscribes to, for tools and other teams; a slanted box: a command nothing in the '
            'team publishes; services and actions in their server; every name relative to the '
            'team). '
            'Left out: parameter services, `/rosout`, `/parameter_events`, `/clock` (from the '
            "simulator to every node) and the simulator's ground truth under `sim/`.\n\n"
            f'```mermaid\n{mermaid(graph)}\n```\n')
    write_text_atomic(args.out, text)
    print(f'node_graph: wrote {args.out} ({len(graph)} nodes)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
