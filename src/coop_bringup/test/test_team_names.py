"""A team's names (coop_bringup.rig): the namespace given to mission.launch.py's team:= and
the check that no name of a team's node crosses to another team in the same domain."""
from __future__ import annotations

import pytest
from coop_bringup.mission import MissionConfig
from coop_bringup.report import MissionError
from coop_bringup.rig import stray_names, team_namespace, team_nodes


class _Graph:
    """What a node discovers of a domain: nodes, and each one's topics."""

    def __init__(self, nodes: dict[tuple[str, str], tuple[list[str], list[str]]]) -> None:
        self.nodes = nodes

    def get_node_names_and_namespaces(self):
        return list(self.nodes)

    def get_subscriber_names_and_types_by_node(self, name, ns):
        return [(t, ['x/msg/Y']) for t in self.nodes[name, ns][0]]

    def get_publisher_names_and_types_by_node(self, name, ns):
        if (name, ns) == ('gone', '/team_a'):
            raise RuntimeError('NodeNameNonExistentError')
        return [(t, ['x/msg/Y']) for t in self.nodes[name, ns][1]]


GRAPH = _Graph({
    ('mapper', '/team_a'): (['/team_a/rover1/stereo/points', '/clock'],
                            ['/team_a/map/voxels', '/rosout', '/tf']),
    ('stereo', '/team_a/rover1'): (['/team_a/rover1/image_raw'], ['/team_b/map/voxels']),
    ('gone', '/team_a'): ([], []),
    ('mapper', '/team_b'): (['/team_b/rover1/stereo/points'], ['/team_b/map/voxels']),
    ('mapper', '/team_ab'): (['/team_ab/x'], []),
})


def test_a_team_is_its_namespace_and_its_nodes_those_in_it():
    assert team_namespace('/team_a/') == 'team_a' and team_namespace('') == ''
    assert team_namespace('site/team_2') == 'site/team_2'
    for bad in ('9a', 'team a', 'a//b', 'a-b'):
        with pytest.raises(MissionError, match='namespace'):
            team_namespace(bad)
    with pytest.raises(MissionError, match='namespace'):
        MissionConfig(team='team-a')
    assert MissionConfig(team='/team_a').team == 'team_a'
    # /team_ab is not under /team_a; the root holds every node
    assert sorted(team_nodes(GRAPH, '/team_a')) == [
        ('gone', '/team_a'), ('mapper', '/team_a'), ('stereo', '/team_a/rover1')]
    assert len(team_nodes(GRAPH, '/')) == 5


def test_a_name_outside_the_team_is_stray_but_the_shared_ones_and_a_node_that_left():
    assert stray_names(GRAPH, '/team_a') == {
        '/team_a/mapper': ['/clock'],                 # the global clock: a team has its own
        '/team_a/rover1/stereo': ['/team_b/map/voxels']}
    assert stray_names(GRAPH, '/team_b') == {}
    assert stray_names(GRAPH, '/') == {}             # at the root no name can cross
