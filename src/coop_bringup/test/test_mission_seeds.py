"""The seeds' runner without the graph: each report judged as its summary judges it, the
table's totals, and a stopped run resumed from the reports it left."""
import json

import pytest
from coop_bringup.mission_seeds import format_result, format_table, judge, parse_seeds, run_seeds
from coop_bringup.report import MissionError


def _report(seed: int, *, error=0.05, coverage=0.93, seated=True) -> dict:
    phases = [{'name': n, 'status': 'ok', 'reason': ''} for n in
              ('identify', 'map', 'place', 'insert')]
    if not seated:
        phases[3].update(status='failed', reason='timeout')
    return {'config': {'seed': seed}, 'targets': {'identification_error': 0.15,
                                                  'coverage': 0.9},
            'identification': {'mean_abs_rel_error': error}, 'mapping': {'coverage': coverage},
            'insertion': {'success': seated, 'reason': 'seated' if seated else 'timeout',
                          'search_views': 2, 'site_error_mm': 21.0, 'align_mm': -1.2,
                          'peak_force_n': 6.0},
            'phases': phases, 'wall_s': 600.0}


def test_seeds_parse_as_ranges_and_lists():
    assert parse_seeds('1-3,7,2') == [1, 2, 3, 7]
    for bad in ('', 'a', '5-3', '-1'):
        with pytest.raises(MissionError):
            parse_seeds(bad)


def test_each_phase_is_judged_against_its_target():
    assert judge(_report(1))['all']
    r = judge(_report(2, error=0.2))                 # identified, but off its target
    assert not r['identify'] and r['insert'] and not r['all']
    r = judge(_report(3, coverage=0.85, seated=False))
    assert not r['map'] and not r['insert'] and r['place']
    # a phase not asked for is not judged
    rep = _report(4, coverage=None)
    rep['phases'][1].update(status='skipped', reason='not asked for')
    assert judge(rep)['all']


def test_a_stopped_run_resumes_from_the_reports_it_left(tmp_path):
    ran = []

    def run_one(seed, run_id):
        ran.append(seed)
        (tmp_path / run_id).mkdir()
        rep = _report(seed, seated=seed != 2)
        (tmp_path / run_id / 'report.json').write_text(json.dumps(rep))
        return rep

    rows = run_seeds([1, 2], run_one, tmp_path, log=lambda m: None)
    assert ran == [1, 2] and [r['insert'] for r in rows] == [True, False]
    rows = run_seeds([1, 2, 3], run_one, tmp_path, log=lambda m: None)
    assert ran == [1, 2, 3] and len(rows) == 3
    saved = json.loads((tmp_path / 'seeds.json').read_text())
    assert saved['complete'] and len(saved['rows']) == 3
    text = format_table(rows)
    assert text.splitlines()[-1] == 'seated 2/3; every phase on target 2/3'
    assert 'timeout' in text.splitlines()[2]
    (tmp_path / 'seed_4').mkdir()                    # a run killed before its report
    with pytest.raises(MissionError, match='unfinished'):
        run_seeds([4], run_one, tmp_path, log=lambda m: None)


def test_an_interrupted_seed_stops_the_batch_and_runs_again_on_resume(tmp_path):
    ran = []

    def run_one(seed, run_id, interrupt=()):
        ran.append(seed)
        (tmp_path / run_id).mkdir()
        rep = _report(seed)
        rep['interrupted'] = seed in interrupt
        (tmp_path / run_id / 'report.json').write_text(json.dumps(rep))
        return rep

    with pytest.raises(KeyboardInterrupt):
        run_seeds([1, 2, 3], lambda s, r: run_one(s, r, interrupt=(2,)), tmp_path,
                  log=lambda m: None)
    assert ran == [1, 2]
    saved = json.loads((tmp_path / 'seeds.json').read_text())
    assert saved['complete'] is False
    assert format_result(saved).splitlines()[-2:] == [
        'seated 1/1; every phase on target 1/1', 'incomplete: 1 of 3 seeds run']
    rows = run_seeds([1, 2, 3], run_one, tmp_path, log=lambda m: None)
    assert ran == [1, 2, 2, 3] and all(r['all'] for r in rows)
    assert (tmp_path / 'seed_2.interrupted-1' / 'report.json').exists()
