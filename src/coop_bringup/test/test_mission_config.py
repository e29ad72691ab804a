"""The mission's options (coop_bringup.mission.MissionConfig and its CLI): every mode is a
member of its StrEnum once the config is built; anything else is refused naming the choices."""
from __future__ import annotations

import pytest
from coop_bringup.mission import PHASES, MissionConfig, PhaseName, main
from coop_bringup.report import MissionError

from coop_common.testing import usage_error


def test_modes_are_members_once_built():
    cfg = MissionConfig(phases=('identify', 'map'), strategy='frontier',
                        identify_strategy='condition')
    assert cfg.phases == (PhaseName.IDENTIFY, PhaseName.MAP)
    assert all(type(p) is PhaseName for p in cfg.phases)
    assert cfg.strategy == 'frontier' and cfg.identify_strategy == 'condition'
    assert type(cfg.strategy).__name__ == 'StrategyName'
    assert MissionConfig().phases == PHASES == tuple(PhaseName)


@pytest.mark.parametrize('changes, message', [
    ({'phases': ('identify', 'fly')},
     "unknown phases ['fly']; choose from identify, map, place, insert"),
    ({'strategy': 'teleport'},
     "strategy must be one of ['random', 'raster', 'max_unmapped', 'min_mapped', "
     "'max_information', 'frontier'], got 'teleport'"),
    ({'identify_strategy': 'shake'},
     "identify_strategy must be one of ['constant', 'information', 'condition', 'd_optimal', "
     "'a_optimal'], got 'shake'"),
    ({'phases': ('identify', 'place')}, "'place' and 'insert' run as one insert goal"),
])
def test_an_unknown_mode_is_refused_naming_the_choices(changes, message):
    with pytest.raises(MissionError) as exc:
        MissionConfig(**changes)
    assert message in str(exc.value)


@pytest.mark.parametrize('argv, message', [
    (['--phases', 'identify,fly'],
     "unknown phases ['fly']; choose from identify, map, place, insert"),
    (['--strategy', 'teleport'],
     "invalid choice: 'teleport' (choose from 'random', 'raster', 'max_unmapped', "
     "'min_mapped', 'max_information', 'frontier')"),
])
def test_the_cli_refuses_an_unknown_mode_before_any_run(argv, message, capsys):
    assert message in usage_error(main, argv, capsys)
