"""tools/node_graph.py turns what the ROS graph reports into a Mermaid flowchart."""
import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location('node_graph', ROOT / 'tools' / 'node_graph.py')
node_graph = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(node_graph)


def test_topics_become_edges_services_stay_in_their_server():
    graph = {'/rover_sim': {'pub': ['/rover1/imu'], 'sub': ['/rover1/cmd_vel'], 'srv': [],
                            'act': []},
             '/rover1/identifier': {'pub': ['/rover1/dynamic_parameters'], 'sub': ['/rover1/imu'],
                                    'srv': ['/rover1/identifier/x'],
                                    'act': ['/rover1/identifier/identify']}}
    text = node_graph.mermaid(graph)
    assert text.startswith('flowchart LR')
    assert 'subgraph rover1["/rover1"]' in text
    sim, ident = 'n1', 'n0'              # ids in sorted order of the full names
    assert f'{sim} -- "rover1/imu" --> {ident}' in text
    assert f'{ident} -- "rover1/dynamic_parameters" --> o0(( ))' in text
    assert '[/"rover1/cmd_vel"/] --> n1' in text
    assert 'action identifier/identify' in text and 'srv identifier/x' in text
    assert node_graph._shown('/map/voxels') and not node_graph._shown('/rosout')
    assert not node_graph._shown('/mapper/get_parameters')
