"""The power-line carrier of §E.4: encoding, the decoder model under noise, malformed trains."""
import numpy as np
import pytest

from coop_braid.carrier import (
    NOISE_BOUND,
    Bus,
    CarrierError,
    Command,
    NoiseBound,
    PulseTrain,
    Timing,
    add_noise,
    commands_between,
    decode,
    decode_stream,
    encode,
    encode_sequence,
)
from coop_braid.stage import LegState

N = 15                                   # the actuators of a 5-stage mast


def test_every_command_round_trips():
    for address in range(N):
        for state in LegState:
            cmd = Command(address, state)
            assert decode(encode(cmd, n_actuators=N), n_actuators=N) == cmd


def test_the_train_is_the_documented_one():
    train = encode(Command(2, LegState.LONG), n_actuators=N)   # word 5
    assert len(train) == (5 + 1) + (2 * N - 1 - 5 + 1) + 1
    assert np.count_nonzero(train.peak_v > 3.25) == 1 and train.peak_v[-1] == 5.0
    t = Timing()
    widths = (train.fall_s - train.rise_s) / t.period_s
    np.testing.assert_allclose(widths, 0.5)
    gaps = np.round((train.rise_s[1:] - train.fall_s[:-1]) / t.period_s, 9)
    assert sorted(set(gaps)) == [0.5, 2.0] and np.flatnonzero(gaps == 2.0).tolist() == [5]
    assert Command(7, LegState.SHORT).stage == 3 and Command(7, LegState.SHORT).leg == 2


@pytest.mark.parametrize('extreme', [False, True])
def test_noise_at_the_bound_addresses_no_wrong_actuator(extreme):
    bus = Bus(20)
    rng = np.random.default_rng(11)
    wrong = missed = 0
    for _ in range(2000):
        cmd = Command(int(rng.integers(0, 60)), LegState(int(rng.integers(0, 2))))
        latched = bus.transmit(add_noise(encode(cmd, n_actuators=60), rng, extreme=extreme))
        wrong += sum(a != cmd.address for row in latched for a in row)
        missed += latched != [[cmd.address]] or bus.decoders[cmd.address].state != cmd.state
    assert wrong == 0 and missed == 0


def test_noise_beyond_the_bound_latches_nothing_rather_than_a_wrong_actuator():
    rng = np.random.default_rng(12)
    wide = NoiseBound(edge_jitter=0.3, amplitude_v=1.0)
    rejected = 0
    for _ in range(500):
        cmd = Command(int(rng.integers(0, N)), LegState(int(rng.integers(0, 2))))
        got = decode(add_noise(encode(cmd, n_actuators=N), rng, bound=wide), n_actuators=N)
        assert got in (None, cmd)
        rejected += got is None
    assert rejected > 100


def _drop(train, i):
    keep = np.arange(len(train)) != i
    return PulseTrain(train.rise_s[keep], train.fall_s[keep], train.peak_v[keep])


def test_malformed_trains_latch_nothing():
    cmd = Command(4, LegState.LONG)
    train = encode(cmd, n_actuators=N)
    # every single lost pulse, the first of burst A and the flag included
    for i in range(len(train)):
        assert decode(_drop(train, i), n_actuators=N) is None, i
    # an extra, well-formed pulse half a period before the train
    t = Timing()
    early = PulseTrain(np.r_[train.rise_s[0] - t.period_s, train.rise_s],
                       np.r_[train.rise_s[0] - t.period_s / 2, train.fall_s],
                       np.r_[2.0, train.peak_v])
    assert decode(early, n_actuators=N) is None
    # a glitch (narrow pulse) in a gap
    glitch = PulseTrain(np.r_[train.rise_s, train.fall_s[2] + 0.1 * t.period_s],
                        np.r_[train.fall_s, train.fall_s[2] + 0.2 * t.period_s],
                        np.r_[train.peak_v, 2.0])
    order = np.argsort(glitch.rise_s)
    glitch = PulseTrain(glitch.rise_s[order], glitch.fall_s[order], glitch.peak_v[order])
    assert decode(glitch, n_actuators=N) is None
    # an address pulse seen as a flag (too high), truncated trains, a flag alone
    high = PulseTrain(train.rise_s, train.fall_s, np.where(np.arange(len(train)) == 3, 4.0,
                                                          train.peak_v))
    assert decode(high, n_actuators=N) is None
    assert decode(PulseTrain(train.rise_s[:10], train.fall_s[:10], train.peak_v[:10]),
                  n_actuators=N) is None
    assert decode(PulseTrain(train.rise_s[-1:], train.fall_s[-1:], train.peak_v[-1:]),
                  n_actuators=N) is None
    # a train for a larger bus (its word is too long for this one)
    assert decode(encode(Command(20, LegState.LONG), n_actuators=30), n_actuators=N) is None
    bus = Bus(5)
    assert bus.transmit(_drop(train, 0)) == [[]]
    assert all(d.latches == 0 for d in bus.decoders)


def test_the_command_sequence_toggles_only_the_legs_that_differ():
    start, goal = np.array([0, 7, 3, 1, 2]), np.array([7, 7, 0, 1, 6])
    cmds = commands_between(start, goal)
    assert [(c.stage, c.leg, c.state) for c in cmds] == [
        (1, 1, LegState.LONG), (1, 2, LegState.LONG), (1, 3, LegState.LONG),
        (3, 1, LegState.SHORT), (3, 2, LegState.SHORT), (5, 3, LegState.LONG)]
    assert commands_between(goal, goal) == []
    bus = Bus(5)
    bus.set_states(start)
    np.testing.assert_array_equal(bus.leg_states(), start)
    stream = add_noise(encode_sequence(cmds, n_actuators=15), np.random.default_rng(3),
                       bound=NOISE_BOUND)
    assert bus.transmit(stream) == [[c.address] for c in cmds]
    np.testing.assert_array_equal(bus.leg_states(), goal)
    assert len(decode_stream(stream, n_actuators=15)) == len(cmds)


def test_bad_commands_are_refused():
    with pytest.raises(CarrierError, match='address'):
        encode(Command(15, LegState.LONG), n_actuators=15)
    with pytest.raises(CarrierError, match='same chain'):
        commands_between([0, 1], [0, 1, 2])
    with pytest.raises(CarrierError, match=r'0\.\.7'):
        Bus(2).set_states([0, 9])
