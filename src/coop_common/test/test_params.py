import pytest

from coop_common.params import ParamSpec, check_values, markdown_table, parse_value

SPECS = {'n': ParamSpec(4, 'count', lo=1, hi=10), 'x': ParamSpec(0.5, 'share', lo=0.0, hi=1.0),
         'mode': ParamSpec('a', 'mode', choices=('a', 'b')), 'on': ParamSpec(True, 'switch')}


def test_parse_value_types_as_the_default():
    assert parse_value(SPECS['n'], '7') == 7 and type(parse_value(SPECS['n'], '7')) is int
    assert parse_value(SPECS['x'], '1e-1') == 0.1
    assert parse_value(SPECS['mode'], 'b') == 'b'
    assert parse_value(SPECS['on'], 'False') is False
    for spec, text in [(SPECS['n'], '7.5'), (SPECS['x'], 'half'), (SPECS['on'], '1')]:
        with pytest.raises(ValueError, match=r'not an? '):
            parse_value(spec, text)


def test_check_values_each_then_the_rule():
    ok = {'n': 4, 'x': 0.5, 'mode': 'a', 'on': True}

    def rule(v):
        return 'n must be even' if v['n'] % 2 else None

    assert check_values(SPECS, ok, rule) == []
    assert check_values(SPECS, ok | {'n': 3}, rule) == ['n must be even']
    # the rule is not asked while a value is out of its own range
    assert check_values(SPECS, ok | {'n': 11, 'x': float('nan')}, rule) == [
        'n must be <= 10, got 11', 'x must be finite, got nan']
    assert check_values(SPECS, ok | {'mode': 'c'}) == ["mode must be one of ['a', 'b'], got 'c'"]


def test_choice_takes_a_member_or_its_string_and_names_the_choices():
    from enum import StrEnum

    from coop_common.params import choice

    class Mode(StrEnum):
        A = 'a'
        B = 'b'

    assert choice(Mode, 'a', 'mode') is Mode.A and choice(Mode, Mode.B, 'mode') is Mode.B
    with pytest.raises(KeyError, match=r"mode must be one of \['a', 'b'\], got 'c'"):
        choice(Mode, 'c', 'mode', error=KeyError)


def test_markdown_table_shows_a_strenum_default_as_its_string():
    from enum import StrEnum

    class Mode(StrEnum):
        FAST = 'fast'
        SLOW = 'slow'

    table = markdown_table({'mode': ParamSpec(Mode.FAST, 'how', choices=list(Mode))})
    assert "| `mode` | str | `'fast'` | `fast`, `slow` | yes | how |" in table


def test_enum_choices_are_named_by_their_strings():
    import enum
    from enum import StrEnum

    class Mode(StrEnum):
        A = 'a'
        B = 'b'

    class Old(str, enum.Enum):  # noqa: UP042 - the pre-StrEnum idiom, on purpose          # str() of such a member is 'Old.X', not its value
        X = 'x'

    assert ParamSpec('a', 'how', choices=tuple(Mode)).choices == ('a', 'b')
    assert ParamSpec('a', 'how', choices=tuple(Mode)).check('mode', 'c') == \
        "mode must be one of ['a', 'b'], got 'c'"
    assert ParamSpec('x', 'how', choices=list(Old)).choices == ('x',)
    assert ParamSpec('a', 'how', choices=tuple(Mode)).check('mode', Mode.B) is None
