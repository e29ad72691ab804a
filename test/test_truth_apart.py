"""Truth judges, never steers (issue #33): the nodes that close the mission's loops do not read
the simulator's world. On the live graph the short mission checks that none subscribes to a
truth topic (test_mission_graph.py); here, that none of their code imports the simulator or
the truth file: every module they load, imported in a fresh interpreter."""
from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

#: the loop nodes' modules (coop_bringup.rig.LOOP_NODES by name)
LOOP_MODULES = ('coop_insertion.master_node', 'coop_insertion.slave_node',
                'coop_insertion.driver_node',
                'coop_id.identifier_node', 'coop_mapping.stereo_node',
                'coop_mapping.mapper_node', 'coop_viewplan.view_planner_node')
#: the truth: the simulator's package, and the truth file's reader
TRUTH = ('rover_sim', 'load_truth')

PROBE = """
import json, sys
for m in sys.argv[1:]:
    __import__(m)
own = {n: getattr(mod, '__file__', None) for n, mod in sys.modules.items()
       if n.split('.')[0] in ('coop_insertion', 'coop_id', 'coop_mapping', 'coop_viewplan',
                              'coop_common', 'rover_sim')}
print(json.dumps(own))
"""


def _names(path: str) -> set[str]:
    tree = ast.parse(Path(path).read_text())
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Name):
            out.add(node.id)
        elif isinstance(node, ast.Attribute):
            out.add(node.attr)
        elif isinstance(node, ast.ImportFrom):
            out.update(a.name for a in node.names)
            out.add(node.module or '')
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return out


def test_the_loop_nodes_load_neither_the_simulator_nor_the_truth_file():
    from coop_bringup.rig import LOOP_NODES
    assert {m.rsplit('.', 1)[1].removesuffix('_node') for m in LOOP_MODULES} == set(LOOP_NODES)
    out = subprocess.run([sys.executable, '-c', PROBE, *LOOP_MODULES], capture_output=True,
                         text=True, timeout=120, check=True).stdout
    loaded = json.loads(out.strip().splitlines()[-1])
    assert not [n for n in loaded if n.split('.')[0] == 'rover_sim'], sorted(loaded)
    readers = []
    for name, path in loaded.items():
        if path and name != 'coop_common.dynparams':   # the truth file reader's own module
            used = _names(path)
            if 'load_truth' in used or any(u.split('.')[0] == 'rover_sim' for u in used):
                readers.append(name)
    assert not readers, readers
    # the check can fail: the rig, which judges by the truth, is caught by it
    assert 'load_truth' in _names(sys.modules['coop_bringup.rig'].__file__)


def test_a_loop_node_on_the_tree_counts_as_reading_the_truth():
    # /tf carries the true poses when the simulator's truth_tf is on
    from coop_bringup.rig import truth_readers
    subs = {'/rover1/master': ['/rover1/odom', '/tf'], '/rover2/slave': ['/rover2/odom'],
            '/live_view': ['/tf', '/sim/rover1/base_pose'], '/rover1/stereo': ['/rover1/odom']}
    assert truth_readers(subs) == {'/rover1/master': ['/tf']}
