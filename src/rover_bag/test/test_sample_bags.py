"""The sample bags in bags/ (tools/record_sample_bags.py): sound, complete, and what their README
says they are. Read without DDS, and once more with the `mcap` package's own reader."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from coop_common.dynparams import PARAM_NAMES, load_truth
from rover_bag.bagio import bag_info, read_messages

BAGS = Path(__file__).resolve().parents[3] / 'bags'
NAMES = ['ident_rover1', 'mapping_two_rovers', 'insertion_site']
pytestmark = pytest.mark.skipif(not all((BAGS / n / 'metadata.yaml').exists() for n in NAMES),
                                reason='sample bags not recorded (tools/record_sample_bags.py)')


def stamps(bag: Path, topic: str) -> np.ndarray:
    return np.array([m.msg.header.stamp.sec * 10**9 + m.msg.header.stamp.nanosec
                     for m in read_messages(bag, [topic])], dtype=np.int64)


def test_all_sample_bags_sound_and_small():
    total = 0
    for name in NAMES:
        info = bag_info(BAGS / name)
        assert info.problems == [] and not info.recovered, name
        assert name in (BAGS / 'README.md').read_text()
        total += sum(f.stat().st_size for f in info.files)
        for f in info.files:
            with f.open('rb') as fh:
                summary = make_reader(fh).get_summary()
            assert summary.statistics.message_count == sum(
                t.count for t in info.topics.values() if t.name in
                {c.topic for c in summary.channels.values()}) or len(info.files) > 1
    assert total <= 20e6


def test_ident_bag():
    bag = BAGS / 'ident_rover1'
    info = bag_info(bag)
    for topic in ('imu', 'inclinometer', 'arm/wrench', 'joint_states'):
        t = stamps(bag, f'/rover1/{topic}')
        assert len(t) >= 1000 and np.all(np.diff(t) == 5_000_000), topic   # gap-free 200 Hz
    (truth,) = [m.msg for m in read_messages(bag, ['/sim/rover1/parameters'])]
    assert list(truth.names) == list(PARAM_NAMES)
    assert truth.values == pytest.approx(load_truth().to_vector())
    arm = np.array([dict(zip(m.msg.name, m.msg.position, strict=False))['arm_joint_1']
                    for m in read_messages(bag, ['/rover1/joint_states'])])
    assert arm.max() - arm.min() > 1.0          # the excitation moved the arm
    # a live identification: one arm command and one estimate per 0.4 s window
    windows = info.topics['/rover1/dynamic_parameters'].count
    assert windows >= 20
    assert info.topics['/rover1/arm/joint_command'].count >= windows


@pytest.mark.parametrize('name', ['mapping_two_rovers', 'insertion_site'])
def test_stereo_bags(name):
    bag = BAGS / name
    info = bag_info(bag)
    for rover in ('rover1', 'rover2'):
        for side in ('left', 'right'):
            topic = f'/{rover}/stereo/{side}/image_raw'
            assert info.topics[topic].count >= 4 * info.duration_s * 0.9, topic
            im = next(read_messages(bag, [topic])).msg
            assert (im.width, im.height, im.encoding) == (320, 240, 'mono8')
            assert len(im.data) == 320 * 240 and np.asarray(im.data).std() > 5
    # left/right pairs share their stamps (one render per pair)
    assert set(stamps(bag, '/rover1/stereo/left/image_raw')) & set(
        stamps(bag, '/rover1/stereo/right/image_raw'))
