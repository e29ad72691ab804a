"""Map contributions: made on the rover, sent compressed, fused once by the mapper."""
from __future__ import annotations

import zlib

import numpy as np
import pytest
from std_msgs.msg import Header

from coop_mapping.contribution import (
    ContributionFormatError,
    decode_keys,
    decode_mask,
    encode_keys,
    encode_mask,
)
from coop_mapping.ledger import Admission, ContributionLedger
from coop_mapping.ros_conv import contribution_to_msg, msg_to_contribution
from coop_mapping.voxelmap import VoxelMap, state_agreement


def _scan(rng: np.random.Generator, n: int = 3000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A wall and a floor seen from a camera near the origin, with stereo-like covariances
    (long along the ray)."""
    origin = np.array([0.0, 0.0, 0.8]) + rng.normal(0, 0.2, 3)
    wall = np.c_[np.full(n // 2, 3.0), rng.uniform(-1.5, 1.5, n // 2), rng.uniform(0, 1.5, n // 2)]
    floor = np.c_[rng.uniform(0.5, 3.0, n - n // 2), rng.uniform(-1.5, 1.5, n - n // 2),
                  np.zeros(n - n // 2)]
    pts = np.r_[wall, floor] + rng.normal(0, 0.005, (n, 3))
    ray = pts - origin
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    s_along, s_across = 0.02, 0.003
    C = (s_along ** 2 - s_across ** 2) * ray[:, :, None] * ray[:, None, :] + \
        s_across ** 2 * np.eye(3)
    cov = C[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]
    return pts, cov, origin


def _wire(vm: VoxelMap, c, seq: int = 1):
    return contribution_to_msg(c, vm, Header(frame_id='map'), source='rover1', session=7,
                               sequence=seq)


def test_a_contribution_does_not_depend_on_the_map_it_is_made_by():
    rng = np.random.default_rng(1)
    full = VoxelMap(0.1)
    for _ in range(3):
        pts, cov, org = _scan(rng)
        full.insert_scan(pts, org, covariances=cov)
    pts, cov, org = _scan(rng)
    a = full.contribution(pts, org, covariances=cov)
    b = VoxelMap(0.1).contribution(pts, org, covariances=cov)
    for name in ('free', 'hit', 'keys', 'info', 'info_offset', 'counts'):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    before = full.keys.copy()
    assert np.array_equal(full.keys, before)       # making one changes nothing


def test_the_map_from_sent_contributions_matches_the_map_from_the_clouds():
    rng = np.random.default_rng(2)
    raw, sent, rover = VoxelMap(0.1), VoxelMap(0.1), VoxelMap(0.1)
    nbytes = cloud_bytes = 0
    for i in range(6):
        pts, cov, org = _scan(rng, 20000)      # about 12 points a voxel, as a 320x240 frame
        raw.insert_scan(pts, org, covariances=cov)
        msg = _wire(rover, rover.contribution(pts, org, covariances=cov), i + 1)
        nbytes += len(msg.free_keys) + len(msg.keys) + len(msg.gaussians) + len(msg.counts)
        cloud_bytes += 36 * len(pts)
        sent.apply(msg_to_contribution(msg, sent))
    assert state_agreement(raw.keys, raw.states(), sent.keys, sent.states()) == 1.0
    assert np.array_equal(raw.logodds, sent.logodds)
    assert np.array_equal(raw.hits, sent.hits)
    h = raw.hits > 0
    d = np.linalg.norm((raw.mean_off[h].astype(float) - sent.mean_off[h].astype(float)), axis=1)
    assert d.max() * raw.resolution < 1e-3          # merged means within 1 mm
    assert nbytes * 10 < cloud_bytes                # and an order of magnitude smaller


def test_contributions_made_with_other_settings_are_refused():
    rng = np.random.default_rng(3)
    pts, cov, org = _scan(rng)
    made = VoxelMap(0.1, ray_subdivision=2)
    msg = _wire(made, made.contribution(pts, org, covariances=cov))
    with pytest.raises(ContributionFormatError, match='ray_subdivision'):
        msg_to_contribution(msg, VoxelMap(0.1))
    with pytest.raises(ContributionFormatError, match=r'0\.2'):
        msg_to_contribution(msg, VoxelMap(0.2, ray_subdivision=2))


def test_damaged_contributions_are_refused_whole():
    rng = np.random.default_rng(4)
    vm = VoxelMap(0.1)
    pts, cov, org = _scan(rng, 500)
    good = _wire(vm, vm.contribution(pts, org, covariances=cov))
    msg_to_contribution(good, vm)

    def damaged(**fields):
        m = _wire(vm, vm.contribution(pts, org, covariances=cov))
        for k, v in fields.items():
            setattr(m, k, v)
        return m
    for bad in (damaged(n_free=good.n_free + 1), damaged(n_keys=good.n_keys - 1),
                damaged(free_keys=bytes(good.free_keys)[:-3]),
                damaged(gaussians=b'not zlib at all'),
                damaged(counts=zlib.compress(np.zeros(good.n_keys, '<u4').tobytes())),
                damaged(gaussians=zlib.compress(np.full(9 * good.n_keys, np.nan,
                                                        '<f2').tobytes())),
                damaged(keys=encode_keys(np.zeros(good.n_keys, np.int64))),
                damaged(free_keys=bytes(good.keys), n_free=good.n_keys)):
        with pytest.raises(ContributionFormatError):
            msg_to_contribution(bad, vm)
    origin_nan = damaged()
    origin_nan.origin.x = float('nan')
    with pytest.raises(ContributionFormatError, match='origin'):
        msg_to_contribution(origin_nan, vm)


def test_key_and_mask_coding_round_trip_and_check_lengths():
    rng = np.random.default_rng(5)
    keys = np.unique(rng.integers(-2 ** 62, 2 ** 62, 1000))
    assert np.array_equal(decode_keys(encode_keys(keys), len(keys)), keys)
    assert decode_keys(encode_keys(keys[:0]), 0).size == 0
    with pytest.raises(ContributionFormatError):
        decode_keys(encode_keys(keys), len(keys) + 1)
    with pytest.raises(ContributionFormatError, match='increasing'):
        decode_keys(encode_keys(keys[::-1]), len(keys))
    mask = rng.random(37) < 0.5
    assert np.array_equal(decode_mask(encode_mask(mask), 37), mask)
    with pytest.raises(ContributionFormatError):
        decode_mask(encode_mask(mask), 90)


def test_the_ledger_fuses_each_contribution_once_and_counts_the_missing():
    led = ContributionLedger()
    assert led.admit('r1', 5, 1) is Admission.NEW
    assert led.admit('r1', 5, 1) is Admission.DUPLICATE
    assert led.admit('r1', 5, 4) is Admission.NEW          # 2 and 3 late or lost
    assert led.missing('r1') == 2
    assert led.admit('r1', 5, 3) is Admission.NEW
    assert led.admit('r1', 5, 4) is Admission.DUPLICATE
    assert led.missing() == 1
    assert led.admit('r1', 5, 2) is Admission.NEW
    assert led.missing() == 0 and led.sources['r1'].contiguous == 4
    assert led.admit('r1', 0, 1) is Admission.BAD_SEQUENCE
    assert led.admit('r1', 5, 0) is Admission.BAD_SEQUENCE
    # a restarted sender: a new session from 1; its old session is closed
    assert led.admit('r1', 9, 1) is Admission.NEW
    assert led.admit('r1', 5, 5) is Admission.OLD_SESSION
    assert led.sources['r1'].sessions == 2
    assert led.admit('r2', 1, 2) is Admission.NEW
    assert led.missing('r2') == 1 and led.missing('r3') == 0
    again = ContributionLedger.from_json(led.to_json())
    assert again.to_json() == led.to_json()
    assert again.admit('r2', 1, 2) is Admission.DUPLICATE
    with pytest.raises(ValueError):
        ContributionLedger.from_json({'r': {'session': 1, 'contiguous': 3, 'early': [4],
                                            'fused': 4, 'sessions': 1}})


def test_the_ledger_is_saved_with_the_map(tmp_path):
    vm = VoxelMap(0.1)
    vm.ledger.admit('rover1', 3, 1)
    vm.ledger.admit('rover1', 3, 3)
    vm.save(tmp_path / 'm.vmap')
    back = VoxelMap.load(tmp_path / 'm.vmap')
    assert back.ledger.to_json() == vm.ledger.to_json()
    assert back.ledger.admit('rover1', 3, 3) is Admission.DUPLICATE
