"""argparse types of the experiment executables."""
import argparse

import pytest

from coop_common.cli import enum_choices, number, output_dir, output_path


def test_number_is_finite_typed_and_in_range():
    f = number(lo=0, hi=180, lo_open=True, hi_open=True)
    assert f('90') == 90.0 and isinstance(f('90'), float)
    for bad in ('0', '180', '-1', 'nan', 'inf', 'x'):
        with pytest.raises(argparse.ArgumentTypeError):
            f(bad)
    n = number(int, lo=1)
    assert n('3') == 3 and isinstance(n('3'), int)
    for bad in ('0', '1.5', 'nan'):
        with pytest.raises(argparse.ArgumentTypeError):
            n(bad)
    assert number(lo=0, hi=1)('1') == 1.0 and number(lo=0, hi=1)('0') == 0.0


def test_output_paths_refused_before_the_run(tmp_path):
    (tmp_path / 'a_file').write_text('x')
    assert output_path(str(tmp_path / 'new' / 'deeper' / 'out.json')).name == 'out.json'
    for bad in (tmp_path / 'a_file' / 'out.json', tmp_path):
        with pytest.raises(argparse.ArgumentTypeError):
            output_path(str(bad))
    assert output_dir(str(tmp_path / 'plots')) == tmp_path / 'plots'
    for bad in (tmp_path / 'a_file', tmp_path / 'a_file' / 'plots'):
        with pytest.raises(argparse.ArgumentTypeError):
            output_dir(str(bad))


def test_figure_path_names_a_format_it_can_write(tmp_path):
    from coop_common.cli import figure_path
    assert figure_path(str(tmp_path / 'a.PNG')) == tmp_path / 'a.PNG'
    assert figure_path(str(tmp_path / 'new' / 'a.pdf')) == tmp_path / 'new' / 'a.pdf'
    for bad in ('a.xyz', 'a', str(tmp_path)):
        with pytest.raises(argparse.ArgumentTypeError):
            figure_path(bad)


def test_enum_choices_name_the_values_as_typed(capsys):
    from enum import StrEnum

    class Mode(StrEnum):
        FAST = 'fast'
        SLOW = 'slow'

    ap = argparse.ArgumentParser(prog='x')
    ap.add_argument('--mode', choices=enum_choices(Mode), default=Mode.FAST.value)
    assert ap.parse_args(['--mode', 'slow']).mode == 'slow'
    with pytest.raises(SystemExit):
        ap.parse_args(['--mode', 'warp'])
    assert "invalid choice: 'warp' (choose from 'fast', 'slow')" in capsys.readouterr().err
