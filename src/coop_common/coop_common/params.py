"""Parameter specifications without rclpy: a node declares them (`node_util.declare_parameters`)
and an off-line tool that runs the node's core on recorded data validates its overrides with the
same ranges and rules (`check_values`), so both refuse the same values with the same reason."""
from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from enum import Enum, StrEnum
from typing import Any, TypeVar

E = TypeVar('E', bound=StrEnum)

__all__ = ['ParamSpec', 'check_values', 'choice', 'markdown_table', 'parse_value']


class ParamSpec:
    """One declared parameter: default, description, optional range/choices, read_only.

    `choices` may be an Enum's members: they are kept as their strings (a parameter is a
    string on the wire), so a refusal names the allowed values as a user types them."""

    def __init__(self, default: Any, description: str, *, lo: float | None = None,
                 hi: float | None = None, choices: Sequence[str] | None = None,
                 read_only: bool = False) -> None:
        self.default = default
        self.description = description
        self.lo, self.hi = lo, hi
        self.choices = tuple(c.value if isinstance(c, Enum) else c
                             for c in choices) if choices else None
        self.read_only = read_only

    def check(self, name: str, value: Any) -> str | None:
        """Reason `value` is not acceptable, or None."""
        if isinstance(value, float) and not math.isfinite(value):
            return f'{name} must be finite, got {value}'
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if self.lo is not None and value < self.lo:
                return f'{name} must be >= {self.lo}, got {value}'
            if self.hi is not None and value > self.hi:
                return f'{name} must be <= {self.hi}, got {value}'
        if self.choices and value not in self.choices:
            return f'{name} must be one of {list(self.choices)}, got {value!r}'
        return None


def choice(kind: type[E], value: Any, name: str, *,
           error: type[Exception] = ValueError) -> E:
    """`value` (a member of the StrEnum `kind` or its string) as the member; `error` naming
    `name` and the choices otherwise. Options typed with a StrEnum take their plain strings
    too (from a parameter, a CLI, a YAML), checked once, at construction."""
    try:
        return kind(value)
    except ValueError:
        raise error(f'{name} must be one of {[m.value for m in kind]}, got {value!r}') from None


def check_values(specs: Mapping[str, ParamSpec], values: Mapping[str, Any],
                 check_all: Callable[[dict[str, Any]], str | None] | None = None) -> list[str]:
    """The reasons `values` (every spec's name) are not acceptable: each value against its spec,
    then, if they all pass, the rule between them (`check_all`); empty when all is well."""
    bad = [r for name, v in values.items() if (r := specs[name].check(name, v))]
    if not bad and check_all is not None and (r := check_all(dict(values))):
        bad.append(r)
    return bad


def parse_value(spec: ParamSpec, text: str) -> Any:
    """`text` as a value of the spec's type (bool, int, float or str, from its default);
    ValueError when it is not one. An int must be integral; a float parameter also takes an
    integer ('60' is 60.0, where `--ros-args -p fov_deg:=60` would be refused by rclpy as an
    INTEGER for a DOUBLE parameter)."""
    d = spec.default
    if isinstance(d, bool):
        if text.lower() not in ('true', 'false'):
            raise ValueError(f'not a bool: {text!r}')
        return text.lower() == 'true'
    if isinstance(d, int):
        try:
            return int(text)
        except ValueError:
            raise ValueError(f'not an integer: {text!r}') from None
    if isinstance(d, float):
        try:
            return float(text)
        except ValueError:
            raise ValueError(f'not a number: {text!r}') from None
    return text


def _cell(text: str) -> str:
    return text.replace('|', '\\|').replace('\n', ' ')


def markdown_table(specs: Mapping[str, ParamSpec]) -> str:
    """The parameters as a Markdown table (name, type, default, range or choices, settable at
    run time, description): a README shows the node's own table, so the two cannot drift."""
    rows = ['| parameter | type | default | range | at run time | description |',
            '|---|---|---|---|---|---|']
    for name, s in specs.items():
        if s.choices:
            rng = ', '.join(f'`{c}`' for c in s.choices)
        elif s.lo is not None or s.hi is not None:
            rng = f'{"" if s.lo is None else s.lo} .. {"" if s.hi is None else s.hi}'
        else:
            rng = ''
        # a StrEnum default is declared as its string: the table shows what ROS sees
        value = s.default.value if isinstance(s.default, StrEnum) else s.default
        default = _cell(repr(value))
        rows.append(f'| `{name}` | {type(value).__name__} | `{default}` | {rng} | '
                    f'{"no" if s.read_only else "yes"} | {_cell(s.description)} |')
    return '\n'.join(rows)
