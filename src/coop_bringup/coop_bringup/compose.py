r"""Several of the project's nodes in one process and one executor (a composed bring-up), the
rclpy counterpart of a component container.

    ros2 run coop_bringup compose coop_insertion/master coop_insertion/slave \
        --ros-args --params-file insertion.yaml -p use_sim_time:=true

Each positional argument names a node as `ros2 run` does (`<package>/<executable>`); the node
class is the one `Node` subclass that executable's module defines. Arguments after
`--ros-args` are ROS's own and reach every node; what is meant for one node uses ROS's own
forms: a parameter file keyed `/**/<node>:`, a remapping `-r <node>:<from>:=<to>`.

One node that cannot start stops the process with its reason; one whose callback raises stops
it with its name and the exception (exit 1). Why and when to compose: docs/design.md.
"""
from __future__ import annotations

import functools
import importlib
import inspect
import re
import sys
from collections.abc import Callable
from importlib import metadata

from rclpy.node import Node

from coop_common.node_util import NodeFailed, run_nodes

from .report import MissionError


class ComposeError(MissionError):
    """A node spec that names no composable node."""


def _normalized(distribution: str) -> str:
    """A distribution's name as packaging compares them (PEP 503: coop_id, coop-id)."""
    return re.sub(r'[-_.]+', '-', distribution).lower()


def node_class(spec: str) -> type[Node]:
    """The node class of `<package>/<executable>`: the one public rclpy Node subclass defined
    in the module of that package's console script."""
    package, sep, executable = spec.partition('/')
    if not sep or not package or not executable:
        raise ComposeError(f'{spec!r}: expected <package>/<executable>')
    scripts = [ep for ep in metadata.entry_points(group='console_scripts')
               if ep.name == executable and ep.dist is not None
               and _normalized(ep.dist.metadata['Name']) == _normalized(package)]
    if not scripts:
        raise ComposeError(f'{spec!r}: package {package!r} has no executable {executable!r}')
    module = importlib.import_module(scripts[0].module)
    classes = [c for name, c in inspect.getmembers(module, inspect.isclass)
               if issubclass(c, Node) and c is not Node and c.__module__ == module.__name__
               and not name.startswith('_')]
    if len(classes) != 1:
        raise ComposeError(f'{spec!r} is not a node executable ({module.__name__} defines '
                           f'{len(classes)} public node classes, not one)')
    return classes[0]


def factories(specs: list[str]) -> list[Callable[[], Node]]:
    """One factory per spec, named after it (the name a failed start is logged under)."""
    out = []
    for spec in specs:
        make = functools.partial(node_class(spec))
        make.__name__ = spec        # type: ignore[attr-defined]
        out.append(make)
    return out


def main(args: list[str] | None = None) -> int:
    """Run the nodes the arguments name in one process (the module docstring); its exit code."""
    argv = list(sys.argv if args is None else args)
    split = argv.index('--ros-args') if '--ros-args' in argv else len(argv)
    specs = argv[1:split]
    if not specs or any(s in ('-h', '--help') for s in specs):
        print(__doc__)
        return 0 if specs else 2
    try:
        made = factories(specs)
    except ComposeError as exc:
        print(f'compose: {exc}', file=sys.stderr)
        return 2
    try:
        return run_nodes(made, argv)
    except NodeFailed as exc:
        print(f'compose: {exc}', file=sys.stderr)
        return 1


if __name__ == '__main__':
    raise SystemExit(main())
