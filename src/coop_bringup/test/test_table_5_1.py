"""table_5_1's bookkeeping without the graph: an attempt the simulator stalled in runs again on a
fresh graph, every attempt is checkpointed, and --resume reuses what a stopped run saved."""
import json
import tempfile
from typing import ClassVar

import pytest
from coop_bringup.rig import Attempt, SimStalled

from coop_bringup import table_5_1


class FakeRig:
    opened = 0
    calls: ClassVar[list] = []
    stall_on: ClassVar[set] = set()

    def __init__(self, **kw):
        self.kw = kw

    def __enter__(self):
        FakeRig.opened += 1
        return self

    def __exit__(self, *exc):
        pass

    def place(self, slot_in, rng):
        pass

    def survey(self):
        return 7

    def stop_mapping(self):
        pass

    def set_slot(self, slot_in):
        self.slot_in = slot_in

    def attempt(self, *, slot_in, placement, seed, timeout_s, max_force_n):
        FakeRig.calls.append((slot_in, placement, seed))
        if (slot_in, seed) in FakeRig.stall_on:
            FakeRig.stall_on.discard((slot_in, seed))
            raise SimStalled('the sim clock stood still for 91 s')
        ok = seed % 2 == 0
        # a fake's outcome: the even seeds seat, aligned to 1 mm with 30 fixes in 40 pairs,
        # the odd ones never got a fix
        return Attempt(slot_in, placement, seed, ok, ok, 'seated' if ok else 'timeout', ok,
                       0.1, 8.0 + seed % 3, 10.0, 20.0, frames=40, fixes=30 if ok else 0,
                       align_mm=-1.0 if ok else None, align_tilt_deg=0.2 if ok else None,
                       rough_site=[3.0, 0.1, 0.4], search_views=1 + seed % 2,
                       site_error_mm=20.0 + seed % 3 if ok else None,
                       curves={'t': [0.0], 'phase': [1]})


@pytest.fixture
def fake_rig(monkeypatch, tmp_path):
    monkeypatch.setattr(table_5_1, 'InsertionRig', FakeRig)
    # the run's work directory (its logs) under the test's, not left in /tmp
    monkeypatch.setattr(tempfile, 'tempdir', str(tmp_path))
    FakeRig.opened, FakeRig.calls, FakeRig.stall_on = 0, [], set()
    return FakeRig


def _run(tmp_path, **kw):
    return table_5_1.run(attempts=3, rows=(5.0, 4.5), placements=('optimal',), seed=1,
                         occlusion_density=0.05, timeout_s=45.0, max_force_n=25.0,
                         site_map=tmp_path / 'site.cmap', checkpoint=tmp_path / 'r.json',
                         log=lambda s: None, **kw)


def test_a_stalled_attempt_runs_again_on_a_fresh_graph(tmp_path, fake_rig):
    fake_rig.stall_on = {(4.5, 1001)}
    res = _run(tmp_path)
    assert fake_rig.opened == 2
    assert fake_rig.calls.count((4.5, 'optimal', 1001)) == 2
    assert [r['optimal_successes'] for r in res['rows']] == [2, 2]     # seeds 1000, 1002
    assert [a['seed'] for a in res['rows'][1]['optimal_attempts']] == [1000, 1001, 1002]
    assert len(res['sim_restarts']) == 1 and res['sim_restarts'][0]['seed'] == 1001
    saved = json.loads((tmp_path / 'r.json').read_text())
    assert saved['complete'] is False and len(saved['rows'][1]['optimal_attempts']) == 3
    assert '1 attempt(s) run again' in table_5_1.format_table(res)


def test_too_many_stalls_end_the_run_with_the_attempts_saved(tmp_path, fake_rig, monkeypatch):
    monkeypatch.setattr(table_5_1, 'MAX_RESTARTS', 0)
    fake_rig.stall_on = {(4.5, 1000)}
    with pytest.raises(SimStalled):
        _run(tmp_path)
    saved = json.loads((tmp_path / 'r.json').read_text())
    assert len(saved['rows'][0]['optimal_attempts']) == 3 and saved['complete'] is False
    assert 'incomplete' in table_5_1.format_table(saved)


def test_resume_reuses_the_saved_attempts(tmp_path, fake_rig, monkeypatch):
    monkeypatch.setattr(table_5_1, 'MAX_RESTARTS', 0)
    fake_rig.stall_on = {(4.5, 1001)}
    with pytest.raises(SimStalled):
        _run(tmp_path)
    fake_rig.calls = []
    res = _run(tmp_path, resume=True)
    assert fake_rig.calls == [(4.5, 'optimal', 1001), (4.5, 'optimal', 1002)]
    assert res['complete'] and [r['optimal_successes'] for r in res['rows']] == [2, 2]
    assert len(res['rows'][0]['optimal_curves']) == 3
    # the time is the attempts' over every sitting, not the last sitting's alone (10 s each)
    assert table_5_1.format_table(res).splitlines()[-1].endswith(
        'the attempts took 1.0 min in all')


def test_the_table_shows_why_a_cell_fails(tmp_path, fake_rig):
    res = table_5_1.run(attempts=3, rows=(4.5,), placements=('optimal', 'random_fixed'),
                        seed=1, occlusion_density=0.05, timeout_s=45.0, max_force_n=25.0,
                        site_map=tmp_path / 'site.cmap', log=lambda s: None)
    row = res['rows'][0]
    assert row['random_fixed_attempts'][1]['fix_rate'] == 0.0
    c = table_5_1.cell_summary(row['optimal_attempts'])
    # seeds 1000 (seated, site 21 mm off), 1001 (never located), 1002 (seated, 20 mm)
    assert c == {'n': 3, 'seated': 2, 'located': 2, 'site_error_mm': 20.5,
                 'search_views': 1.0, 'reached_descent': 2, 'fix_rate': 0.75,
                 'align_mm': 1.0, 'align_tilt_deg': 0.2, 'false_seated': 0,
                 'missed_seated': 0, 'peak_force_n': 10.0}
    # the slave calling a card seated the truth denies, and one the truth seated it never
    # called: each is a disagreement of its own kind
    lie = dict(row['optimal_attempts'][0], seated=False, success=False)
    miss = dict(row['optimal_attempts'][0], action_success=False, success=False)
    c = table_5_1.cell_summary([*row['optimal_attempts'], lie, miss, miss])
    assert (c['seated'], c['false_seated'], c['missed_seated']) == (2, 1, 2)
    text = table_5_1.format_table(res)
    assert 'random_fixed' in text.splitlines()[1]
    assert any(line.split()[:9] == ['Medium', 'optimal', '2/3', '2', '1', '20', '2', '0.75',
                                    '1.0']
               for line in text.splitlines()), text


def test_rows_give_their_own_attempts_and_placements():
    rows = table_5_1.parse_rows(table_5_1.DEFAULT_ROWS, attempts=10,
                                placements=table_5_1.TABLE_PLACEMENTS)
    assert rows[:3] == [(w, 10, table_5_1.TABLE_PLACEMENTS) for w in (5.0, 4.5, 4.375)]
    assert rows[3] == (4.2925, 30, ('optimal',))
    assert table_5_1.parse_rows('5::random+optimal', attempts=2, placements=('optimal',)) == \
        [(5.0, 2, ('random', 'optimal'))]
    for bad, why in (('4.2', 'wider'), ('5:0', 'at least one'), ('5:2:best', 'placements'),
                     ('5:1:optimal:x', 'width'), ('', 'no rows'), ('5,5.0', 'twice'),
                     ('5:1:optimal+optimal', 'twice')):
        with pytest.raises(ValueError, match=why):
            table_5_1.parse_rows(bad, attempts=1, placements=('optimal',))


def test_resume_refuses_attempts_of_other_settings(tmp_path, fake_rig, monkeypatch):
    """A checkpoint of another experiment (an older table format, another force limit) is not
    mixed into this one: every attempt runs again."""
    _run(tmp_path)
    saved = json.loads((tmp_path / 'r.json').read_text())
    saved['settings']['format'] = table_5_1.TABLE_FORMAT - 1
    (tmp_path / 'r.json').write_text(json.dumps(saved))
    fake_rig.calls = []
    said = []
    table_5_1.run(attempts=3, rows=(5.0, 4.5), placements=('optimal',), seed=1,
                  occlusion_density=0.05, timeout_s=45.0, max_force_n=25.0,
                  site_map=tmp_path / 'site.cmap', checkpoint=tmp_path / 'r.json',
                  log=said.append, resume=True)
    assert len(fake_rig.calls) == 6 and any('other settings' in s for s in said)


def test_thin_curves_keeps_every_phase_change_and_the_ends():
    n = 1000
    t = [0.01 * i for i in range(n)]
    phase = [0 if i < 333 else 1 if i < 700 else 2 for i in range(n)]
    c = {'t': t, 'phase': phase, 'displacement_m': [1e-3 * i for i in range(n)],
         'angle_rad': [0.0] * n, 'force': [[0.1234567, 0.0, -1.0]] * n}
    thin = table_5_1.thin_curves(c, dt_s=0.25)
    assert thin['t'][0] == 0.0 and thin['t'][-1] == round(t[-1], 3)
    assert len(thin['t']) <= n * 0.01 / 0.25 + 4
    # the samples where the phase changes are kept: their times are there
    assert {3.33, 7.0} <= set(thin['t'])
    assert all(len(v) == len(thin['t']) for v in thin.values())
    assert thin['force'][0] == [0.123, 0.0, -1.0]
    assert table_5_1.thin_curves({}) == {}


def test_each_placement_is_plotted_from_the_hardest_row_that_ran_it(tmp_path, fake_rig,
                                                                   monkeypatch):
    """A last row of the optimal placement alone (the 1 % row) does not hide the random plot."""
    res = table_5_1.run(attempts=2, rows=[(5.0, 2, ('optimal', 'random')), (4.5, 2, ('optimal',))],
                        placements=('optimal', 'random'), seed=1, occlusion_density=0.05,
                        timeout_s=45.0, max_force_n=25.0, site_map=tmp_path / 'site.cmap',
                        log=lambda s: None)
    seen = []
    monkeypatch.setattr(table_5_1, 'plot_curves',
                        lambda c, title, path: seen.append((title, path.name)) or path)
    table_5_1.plot(res, tmp_path)
    assert [(t.split(',')[0], n) for t, n in seen] == [
        ('Medium (4.5 in)', 'fig_5_13_optimal.png'), ('Easy (5.0 in)', 'fig_5_13_random.png')]
