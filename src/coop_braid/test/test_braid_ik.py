"""The braid_ik experiment at reduced size: its JSON keys, its table and its plots."""
import json

from coop_braid import braid_ik


def test_braid_ik_reduced_run_writes_the_documented_keys(tmp_path, capsys):
    out = tmp_path / 'braid.json'
    assert braid_ik.main(['--targets', '8', '--stages', '3,5', '--carrier', '100', '--json',
                          str(out), '--plots', str(tmp_path / 'img'), '--seed', '2']) == 0
    res = json.loads(out.read_text())
    for n in (3, 5):
        methods = res[f'n{n}']['methods']
        assert set(methods) == {'exhaustive', 'beam', 'combinatorial', 'genetic'}
        for m in methods.values():
            assert {'median_ms', 'p95_ms', 'pos_err_mm', 'ang_err_deg'} <= set(m)
        assert res[f'n{n}']['reach_m'] > 0
    assert 0.0 <= res['within_10pct_of_exhaustive'] <= 1.0
    assert res['best_median_ms_n20'] is None
    assert res['carrier']['wrong_actuators'] == 0 and res['carrier']['commands'] == 100
    printed = capsys.readouterr().out
    assert printed.startswith(braid_ik.format_json(res))
    assert (tmp_path / 'img' / 'braid_workspace_n5.png').is_file()
    assert (tmp_path / 'img' / 'braid_ik_errors.png').is_file()


def test_bad_options_are_usage_errors(capsys):
    for argv in (['--stages', '5,x'], ['--stages', '0'], ['--targets', '0']):
        try:
            braid_ik.main(argv)
        except SystemExit as exc:
            assert exc.code == 2
        else:
            raise AssertionError(argv)
    assert 'chain lengths' in capsys.readouterr().err
