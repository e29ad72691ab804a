"""App. A.4's two-rover segment insertion core (coop_insertion.segment): surrogate sensing
against hand cases and against rover_sim's true grasp forces, the slave's silent-partner hold,
the master's search and seat verdict."""
from __future__ import annotations

import numpy as np
import pytest

from coop_common.rover_geometry import (
    ARM_JOINTS,
    ARM_MASS,
    NOMINAL_CG_TO_ARM,
    arm_gravity_moment,
    card_in_base,
)
from coop_insertion.errors import InsertionError
from coop_insertion.segment import (
    MasterSettings,
    PartModel,
    PartReference,
    SegmentMaster,
    SegmentPhase,
    SegmentSlave,
    force_on_part,
    internal_force,
    partner_force,
)

R2 = np.array(NOMINAL_CG_TO_ARM)
Q = np.array([0.05, -0.5, 1.1, -0.6])


def test_force_on_part_inverts_the_sensor_model():
    """A part force f and couple m at the grasp make the arm-base sensor read the arm's weight
    plus f, and the arm's gravity moment plus r x f + m: force_on_part gives f and m back."""
    f, m = np.array([0.7, -0.2, 2.4]), np.array([0.01, -0.03, 0.02])
    r = card_in_base(Q, R2)[:3, 3] - R2
    reading_f = ARM_MASS * 9.81 * np.array([0.0, 0.0, 1.0]) + f
    reading_m = arm_gravity_moment(Q) + np.cross(r, f) + m
    got_f, got_m = force_on_part(reading_f, reading_m, Q, R2)
    np.testing.assert_allclose(got_f, f, atol=1e-12)
    np.testing.assert_allclose(got_m, m, atol=1e-12)
    with pytest.raises(InsertionError):
        force_on_part(np.array([np.nan, 0, 0]), np.zeros(3), Q, R2)


def test_partner_force_and_internal_force_by_hand():
    """Newton on a 0.5 kg part at rest: the partner carries what one's own does not; an equal
    share leaves no internal force, a squeeze is half the difference."""
    model = PartModel(mass_kg=0.5)
    own = np.array([0.0, 0.0, 2.0])
    np.testing.assert_allclose(partner_force(model, np.zeros(3), own), [0.0, 0.0, 2.905])
    np.testing.assert_allclose(model.share(np.zeros(3)), [0.0, 0.0, 2.4525])
    np.testing.assert_allclose(internal_force([3.0, 0.0, 2.45], [-3.0, 0.0, 2.45]),
                               [3.0, 0.0, 0.0])
    # accelerating up at 1 m/s^2 needs m (a + g) in all
    np.testing.assert_allclose(partner_force(model, np.array([0.0, 0.0, 1.0]), own),
                               [0.0, 0.0, 0.5 * 10.81 - 2.0])


def _slave(t0: float = 0.0) -> SegmentSlave:
    return SegmentSlave(PartModel(), grasp=np.array([0.0, 1.5, 0.4]),
                        master_grasp=np.array([0.0, 0.0, 0.4]), t0=t0)


def test_slave_follows_the_reference_and_yields_to_force():
    """With its share it rides the reference at the grasp offset; pushed up harder than its
    share, it gives way downwards, no faster than its speed limit."""
    s = _slave()
    share = PartModel().share(np.zeros(3))
    for k in range(1, 11):
        t = 0.01 * k
        ref = PartReference(t, np.array([0.01 * k, 0.0, 0.4]), np.zeros(3), np.zeros(3))
        target, _ = s.step(t, ref, share)
    np.testing.assert_allclose(target, [0.1, 1.5, 0.4], atol=1e-9)
    z0 = target[2]
    for k in range(11, 111):
        t = 0.01 * k
        ref = PartReference(t, np.array([0.1, 0.0, 0.4]), np.zeros(3), np.zeros(3))
        target, _ = s.step(t, ref, share + np.array([0.0, 0.0, 10.0]))
    assert target[2] < z0 - 0.01
    assert z0 - target[2] <= s.s.max_speed_m_s * 1.0 + 1e-9
    assert s.internal_estimate[2] < -4.0      # it pushed 10 N over its share: -5 N internal


def test_slave_holds_when_the_master_falls_silent():
    """A reference that stops coming: the slave stops where it is (never extrapolates the last
    plan) and only yields to the force it feels, back to the part's static share."""
    s = _slave()
    share = PartModel().share(np.zeros(3))
    ref = None
    for k in range(1, 51):
        t = 0.01 * k
        ref = PartReference(t, np.array([0.0, 0.0, 0.4 - 0.01 * t]), np.array([0, 0, -0.01]),
                            np.zeros(3))
        s.step(t, ref, share)
    held, _ = s.step(0.51, None, share)
    for k in range(52, 400):
        target, _ = s.step(0.01 * k, None, share)
    assert s.silent
    np.testing.assert_allclose(target, held, atol=1e-9)


def _master(**kw: float) -> SegmentMaster:
    return SegmentMaster(PartModel(), grasp=np.array([0.0, 0.0, 0.40]), stage_x=0.05,
                         stage_top_z=0.28, stage_depth_m=0.05, t0=0.0,
                         settings=MasterSettings(**kw))


def _run_master(m: SegmentMaster, t0: float, t1: float, *, force, pitch=0.0,
                grasp=None, until=SegmentPhase.FAILED) -> float:
    share = m.model.share(np.zeros(3))
    t = t0
    while t < t1 and m.phase not in (SegmentPhase.DONE, SegmentPhase.FAILED, until):
        t += 0.01
        g = m.pos if grasp is None else grasp
        m.step(t, g, share + force(m), np.zeros(3), pitch)
    return t


def test_master_searches_out_from_its_belief_by_the_clearance():
    """Each wall contact moves the next try out by the clearance, alternately either side of
    the belief, and the search ends with the reason past its half-width."""
    m = _master(search_halfwidth_m=0.01)
    t = _run_master(m, 0.0, 20.0, force=lambda _: np.zeros(3),   # lift and settle
                    until=SegmentPhase.DESCEND)
    assert m.phase is SegmentPhase.DESCEND
    tried = []
    while m.phase is not SegmentPhase.FAILED and t < 200:
        # the part meets a wall top 2 mm below the mouth, wherever it is
        t = _run_master(m, t, t + 30, until=SegmentPhase.BACK_OFF, force=lambda mm: np.array(
            [0.0, 0.0, -3.0 if mm.pos[2] - 0.02 < 0.278 else 0.0]))
        if m.phase is SegmentPhase.BACK_OFF:
            t = _run_master(m, t, t + 30, until=SegmentPhase.DESCEND,
                            force=lambda _: np.zeros(3))
        tried.append(round(m.target_x - 0.05, 4))
    assert tried[:4] == [0.002, -0.002, 0.004, -0.004]
    assert m.phase is SegmentPhase.FAILED and 'searched +-10 mm' in m.reason


def test_master_seats_only_level_at_the_floor():
    """Pressed at the believed floor with the part level: seated. The same press with the part
    turned off level (a corner on an edge) is not, and ends failed with the reason."""
    for pitch, want in ((0.0, SegmentPhase.DONE), (0.03, SegmentPhase.FAILED)):
        m = _master(touch_pitch_rad=1.0)
        t = _run_master(m, 0.0, 20.0, force=lambda _: np.zeros(3), until=SegmentPhase.DESCEND)
        _run_master(m, t, t + 30, pitch=pitch, force=lambda mm: np.array(
            [0.0, 0.0, -4.0 if mm.pos[2] - 0.02 < 0.2305 else 0.0]))
        assert m.phase is want, m.reason
        assert (m.reason == 'seated') == (want is SegmentPhase.DONE)


def test_surrogate_estimate_matches_the_simulators_true_partner_force():
    """rover_sim: two rovers grasp a 0.8 kg segment and hold it; the slave's estimate of the
    master's force, from its own F/T and the part's model, is the simulator's true grasp force
    of the master to within 0.3 N (the F/T noise is 0.08 N; the rest is the quasi-static arm
    model and the nominal arm mount, 1 cm from the truth)."""
    from coop_common.dynparams import load_truth
    from rover_sim.config import NoiseConfig, SimConfig
    from rover_sim.segment import SegmentSpec, StageSpec
    from rover_sim.world import World
    cfg = SimConfig(rovers=2, occlusion_density=0.0, stereo_rate_hz=0.0, seed=3,
                    noise=NoiseConfig(encoder_rad=0.0077))
    model = PartModel(mass_kg=0.8)
    with World(cfg, [load_truth()] * 2, card=False) as w:
        for _ in range(100):
            w.step()
        seg = w.grasp_segment(SegmentSpec(mass_kg=0.8), StageSpec(centre_x=-1.6, top_z=0.2))
        errs = []
        slave = SegmentSlave(model, grasp=np.zeros(3), master_grasp=np.zeros(3), t0=w.time_s)
        for k in range(400):
            w.step()
            rd = w.sense(1)
            f, _ = force_on_part(rd.force, rd.torque, rd.joint_positions[:4], R2)
            slave.step(w.time_s, None, f)
            if k >= 200:
                errs.append(np.linalg.norm(slave.partner_estimate - seg.last.grasp_force[0]))
        assert seg.last.grasp_force[:, 2].sum() == pytest.approx(0.8 * 9.81, rel=0.02)
        assert float(np.sqrt(np.mean(np.square(errs)))) < 0.3
        assert len(ARM_JOINTS) == 4
