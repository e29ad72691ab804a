"""Identification from a bag without DDS (coop_id.offline): the sample stream is read and the
core runs in the node's windows."""
import json
from pathlib import Path

import numpy as np
import pytest

from coop_id import offline
from coop_id.identifier_core import IdentifierConfig

BAG = Path(__file__).resolve().parents[3] / 'bags' / 'ident_rover1'


@pytest.fixture(scope='module')
def samples():
    if not (BAG / 'metadata.yaml').exists():
        pytest.skip('sample bag not recorded')
    return offline.bag_samples(BAG)


def test_bag_samples_join_the_three_sensors_on_their_stamps(samples):
    stamps, rows = samples
    assert rows.shape[1] == 14 and len(rows) >= 1000
    assert np.all(np.diff(stamps) == 5_000_000)              # 200 Hz, nothing lost or repeated
    assert np.abs(rows[:, 2].mean() - 9.81) < 0.2               # specific force z at rest ~ g


def test_identify_rows_runs_whole_windows_and_reports_consistently(samples):
    _, rows = samples
    cfg = IdentifierConfig()
    report = offline.identify_rows(rows, cfg)
    assert report.values.shape == (22,) and np.all(np.isfinite(report.values))
    assert report.consistent
    with pytest.raises(offline.BagError):
        offline.identify_rows(rows[:10], cfg)


def test_truth_is_read_from_the_bag(samples):
    truth = offline.bag_truth(BAG)
    assert truth is not None and truth[0] == 3.0


def test_a_bag_without_the_stream_is_a_clear_error():
    other = BAG.parent / 'mapping_two_rovers'
    if not (other / 'metadata.yaml').exists():
        pytest.skip('sample bag not recorded')
    with pytest.raises(offline.BagError, match='imu'):
        offline.bag_samples(other)


def _without_truth(dst: Path) -> Path:
    """ident_rover1 as a real rover would record it: the sensor streams, no simulator truth."""
    from rover_bag.bagio import BagWriter, read_messages
    with BagWriter(dst) as w:
        for m in read_messages(BAG, list(offline.ident_topics('rover1')), raw=True):
            w.add_topic(m.topic, m.msgtype)
            w.write(m.topic, m.t_ns, m.msg)
    return dst


def test_a_real_rovers_bag_has_no_truth_and_is_still_identified(samples, tmp_path, capsys):
    from coop_id.table_2_1 import main
    bag = _without_truth(tmp_path / 'hw')
    assert offline.bag_truth(bag) is None                 # was the rover_bag error, uncaught
    assert main(['--bag', str(bag), '--json', str(tmp_path / 'r.json')]) == 0
    out = capsys.readouterr().out
    assert 'Mass (kg)' in out and '% Avg. Error' not in out
    assert '"mean_abs_rel_error": null' in (tmp_path / 'r.json').read_text()
    # the printed table is what docs/results makes of the JSON (no True column here)
    from coop_id.table_2_1 import format_bag
    assert out == format_bag(json.loads((tmp_path / 'r.json').read_text())) + '\n'
