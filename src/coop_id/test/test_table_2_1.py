"""The experiment executable at reduced size (CLI, JSON keys, plots)."""
import json

import pytest

from coop_common.testing import usage_error
from coop_id.table_2_1 import format_json, format_sim, main, time_to


def test_cli_writes_the_issue_json_keys(tmp_path, capsys):
    out = tmp_path / 'r.json'
    rc = main(['--seeds', '1', '--duration', '2', '--strategies', 'constant,information',
               '--json', str(out), '--plots', str(tmp_path / 'plots')])
    assert rc == 0
    text = capsys.readouterr().out
    assert 'Table 2-1' in text and 'Stiffness th_p' in text and '% Avg. Error' in text
    doc = json.loads(out.read_text())
    assert doc['seeds'] == 1
    for s in ('constant', 'information'):
        st = doc['strategies'][s]
        assert 0 <= st['mean_abs_rel_error'] < 10
        assert st['time_to_20pct_s'] is None or st['time_to_20pct_s'] > 0
        assert set(st['per_parameter']['mass']) >= {'estimate', 'std'}
        assert len(st['per_parameter']) == 22
    assert (tmp_path / 'plots' / 'fig_2_6_information_k_pitch.png').stat().st_size > 1000
    # the printed table is what docs/results makes of the JSON
    assert text.startswith(format_json(doc) + '\n')


def test_without_accelerometer_the_rotational_subset_is_summed_up(tmp_path, capsys):
    out = tmp_path / 'r.json'
    assert main(['--seeds', '1', '--duration', '2', '--strategies', 'constant,information',
                 '--no-accelerometer', '--json', str(out)]) == 0
    text = capsys.readouterr().out
    doc = json.loads(out.read_text())
    assert text.startswith(format_json(doc) + '\n')
    # mass, damping and stiffness in x, y, z need the accelerometer: flagged in every seed
    for s in ('constant', 'information'):
        pp = doc['strategies'][s]['per_parameter']
        assert all(pp[p]['observable_fraction'] == 0 for p in ('mass', 'b_z', 'k_x'))
    assert 'without accelerometer, over the ' in text


def test_sim_mode_prints_its_json(tmp_path, capsys, monkeypatch):
    """`--sim` prints through format_sim(its JSON); the nodes are replaced by a fixed result."""
    import numpy as np

    import coop_id.sim_mode
    from coop_common.dynparams import PARAM_NAMES, load_truth
    truth = load_truth().to_vector()
    n = len(PARAM_NAMES)

    integrators = []

    def fake(*, duration_s, strategy, noise, integrator, lockstep):
        integrators.append(integrator)
        est = truth * (1.1 if strategy == 'constant' else 1.01) + 0.001
        return {'success': True, 'message': f'{strategy}: 22/22 observable', 'truth': truth,
                'estimate': est, 'std': np.full(n, 0.002),
                'observable': [True] * (n - 1) + [False],
                'mean_abs_rel_error': 0.05, 'samples': 2001, 'rejected': 0, 'logs': '/tmp/x'}
    monkeypatch.setattr(coop_id.sim_mode, 'run_sim_identification', fake)
    out = tmp_path / 's.json'
    assert main(['--sim', '--strategies', 'information,constant', '--json', str(out)]) == 0
    text = capsys.readouterr().out
    doc = json.loads(out.read_text())
    assert text == format_sim(doc) + '\n'
    k_yaw = next(line for line in text.splitlines() if line.startswith('Stiffness th_v'))
    assert k_yaw.endswith('*') and text.count('*') == 2 + 1     # + the header's legend
    assert doc['strategies']['constant']['per_parameter']['mass']['estimate'] == \
        pytest.approx(3.301)
    assert integrators == ['explicit', 'explicit'] and doc['integrator'] == 'explicit'
    assert main(['--sim', '--strategies', 'information', '--integrator', 'implicit', '--json',
                 str(out)]) == 0
    assert integrators[-1] == 'implicit' and json.loads(out.read_text())['integrator'] == \
        'implicit'


def test_cli_rejects_bad_arguments(tmp_path):
    with pytest.raises(SystemExit):
        main(['--strategies', 'constant,magic'])
    bad = tmp_path / 'truth.yaml'
    bad.write_text('mass: -1\n')
    assert main(['--truth', str(bad), '--seeds', '1', '--duration', '1']) == 2


@pytest.mark.parametrize('args, reason', [
    (['--duration', '0.2'], '--duration: 0.2 must be >= 0.4'),     # no identification window
    (['--duration', 'nan'], "--duration: 'nan' is not finite"),
    (['--first-seed', '-1'], '--first-seed: -1 must be >= 0'),
    (['--seeds', '1000000000'], '--seeds: 1000000000 must be <= 10000'),
    (['--strategies', 'constant,constant'], 'a strategy is listed twice'),
    (['--strategies', 'shake'], "unknown strategies ['shake']; choose from constant,"
                                'information,condition,d_optimal,a_optimal'),
    (['--sim', '--integrator', 'rk4'], "invalid choice: 'rk4' (choose from 'implicit', "
                                       "'explicit')"),
    (['--json', '{tmp}'], 'is a directory'),
    (['--plots', '{tmp}/f'], 'is not a directory'),
    (['--bag', '{tmp}/none'], 'does not exist'),
    (['--sim', '--bag', '{tmp}'], '--sim and --bag are two different sources'),
    (['--bag', '{tmp}', '--seeds', '3'], '--seeds: not used with --bag'),
    (['--bag', '{tmp}', '--seeds=30'], '--seeds: not used with --bag'),      # at its default
    (['--bag', '{tmp}', '--see', '3'], 'unrecognized arguments'),             # no abbreviation
    (['--sim', '--plots', '{tmp}'], '--plots: not used with --sim'),
    (['--rover', 'rover2'], '--rover: not used with the model-level study'),
])
def test_cli_refuses_before_any_work(tmp_path, capsys, args, reason):
    """Each a usage error (exit 2) before a run: they were tracebacks after the run (--json,
    --plots), an UnboundLocalError (no window), or silently ignored options."""
    (tmp_path / 'f').write_text('a file')
    assert reason in usage_error(main, [a.format(tmp=tmp_path) for a in args], capsys)


def test_time_to_settles():
    assert time_to([1, 2, 3, 4], [0.5, 0.1, 0.3, 0.1], 0.2) == 4
    assert time_to([1, 2, 3], [0.5, 0.3, 0.3], 0.2) is None
    assert time_to([1, 2], [0.1, 0.1], 0.2) == 1


def test_installed_like_ros2_run():
    import subprocess

    from coop_common.testing import executable_path
    for exe in ('table_2_1', 'identifier'):
        assert executable_path('coop_id', exe).is_file()
    out = subprocess.run([str(executable_path('coop_id', 'table_2_1')), '--help'],
                         check=False, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and '--strategies' in out.stdout
