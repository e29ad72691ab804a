"""The slave's insertion loop (slave.py) on rover_sim's world core, no DDS: fixes are the true
marker positions in a fixed camera's frame plus stereo-like noise at 4 Hz; the arm, base, F/T and
odometry are the simulator's. Checks the loop's phases end to end and the bad-input rules."""
import math

import numpy as np
import pytest

from coop_insertion.errors import InsertionError
from coop_insertion.slave import Phase, SlaveController
from coop_insertion.task import TaskModel

rover_sim = pytest.importorskip('rover_sim.world')
from coop_insertion.force_trials import run_trial  # noqa: E402
from rover_sim.worldgen import INCH  # noqa: E402


def _run(slot_in: float, seed: int, **kw):
    trial, st, phases, ctl = run_trial(slot_in, seed, **kw)
    return st, trial.seated, trial.max_penetration_mm * 1e-3, phases, ctl


def test_an_easy_insertion_seats_the_card_through_every_phase():
    st, seated, pen, phases, ctl = _run(5.0, 1)
    assert st.done and st.success, st.reason
    assert seated
    assert pen <= 5e-4
    assert phases == [Phase.READY, Phase.VISUAL_SERVO, Phase.FORCE_INSERT, Phase.DONE]
    assert 0.0 < ctl.peak_force_n <= 25.0


def test_without_vision_the_slave_stops_short_and_never_descends():
    st, seated, pen, phases, ctl = _run(5.0, 2, vision=False, sim_s=20.0)
    assert not st.done and not st.descending and not seated
    assert Phase.FORCE_INSERT not in phases
    assert pen == 0.0


def test_bad_inputs_are_refused():
    with pytest.raises(InsertionError):
        SlaveController(TaskModel(), [0.0, math.nan, 0.1])
    ctl = SlaveController(TaskModel(), [0.01, 0.3, 0.1])
    with pytest.raises(InsertionError, match='before the first state'):
        ctl.step(0.0)
    with pytest.raises(InsertionError):
        ctl.add_state(0.0, [0.0] * 3, [0.0] * 3, [0.0] * 6)


def test_a_card_tilted_on_one_corner_is_not_seated():
    from coop_insertion.contact import ContactState
    from coop_insertion.slave import card_seated
    geo = {'slot_depth_m': 0.030, 'card_width_m': 4.25 * INCH, 'seat_angle_rad': 0.02}
    corner = ContactState.CORNER_ON_BOTTOM
    # 29.2 mm at the lower edge's centre, tilted 2 deg: the higher corner is 27.3 mm down
    assert not card_seated(corner, 0.0292, math.radians(2.0), stalled=True, **geo)
    assert not card_seated(corner, 0.0295, -0.03, stalled=False, **geo)
    # flat: at the floor within 1 mm, or stalled within 4 mm against the bottom
    assert card_seated(corner, 0.0296, math.radians(0.5), stalled=False, **geo)
    assert not card_seated(corner, 0.0265, 0.0, stalled=True, **geo)   # one corner: tilted
    assert card_seated(ContactState.TWO_POINT, 0.0265, 0.0, stalled=True, **geo)
    assert not card_seated(corner, 0.0265, 0.0, stalled=False, **geo)
    assert not card_seated(ContactState.FREE, 0.0265, 0.0, stalled=True, **geo)
    assert card_seated(ContactState.SEATED, 0.020, 0.0, stalled=False, **geo)
    # at the floor by the estimate, but nothing pushes back: the estimate is off, go on
    assert not card_seated(ContactState.FREE, 0.0303, math.radians(0.8), stalled=False, **geo)
    assert not card_seated(ContactState.CORNER_ON_WALL, 0.0300, 0.0, stalled=False, **geo)


def test_the_abort_needs_a_force_sustained_over_three_readings():
    from coop_insertion.slave import ABORT_SAMPLES

    def force_phase():
        ctl = SlaveController(TaskModel(), [0.01, 0.3, 0.1], max_force_n=20.0)
        ctl.phase, ctl._tare, ctl._last_force_step = Phase.FORCE_INSERT, np.zeros(6), 1e9
        return ctl

    q = [0.0, 0.6, -1.0, 0.4]
    ctl = force_phase()       # one 73 N reading among small ones: an impact's ring, go on
    for k, f in enumerate([1.0, 73.0, 1.0, 1.0]):
        ctl.add_state(0.005 * k, q, [0.0] * 3, [0.0, 0.0, f, 0.0, 0.0, 0.0])
        assert not ctl.step(0.005 * k).status.done
    assert ctl.peak_force_n == 73.0
    ctl = force_phase()       # three in a row above 1.5 x 20 N: abort
    for k in range(ABORT_SAMPLES):
        ctl.add_state(0.005 * k, q, [0.0] * 3, [0.0, 0.0, 40.0, 0.0, 0.0, 0.0])
        st = ctl.step(0.005 * k).status
    assert st.done and not st.success and 'abort limit 30.0 N' in st.reason
