"""The PyBullet world without DDS: equilibrium, F/T against Newton-Euler on the arm,
inclinometer against the compliance, determinism, noise scales, rendering, driving."""
import dataclasses
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pybullet as pb
import pytest

from coop_common.dynparams import BaseParameters, load_truth
from rover_sim.compliance import matrix_to_rpy
from rover_sim.config import NoiseConfig, SimConfig
from rover_sim.render_worker import _START
from rover_sim.rover_model import ARM_MASS, SENSOR_MASS
from rover_sim.world import World

QUIET = NoiseConfig(fraction=0.0)


def one_rover(noise=QUIET, truth=None, **kw) -> World:
    return World(SimConfig(rovers=1, noise=noise, stereo_rate_hz=0.0, **kw),
                 [truth or load_truth()])


def excite(world: World, seconds: float, warmup: float = 2.0):
    """Arm to the Eq. 2-21 offset, then f(t) = pi/4 + 2pi/9 sin(pi/2 t) on arm joint 2."""
    world.command_arm(0, ['arm_joint_1', 'arm_joint_2'], [warmup], [[0.0, np.pi / 4]])
    for _ in range(int(warmup / world.dt) + 40):
        world.step()
    ts = np.arange(0.02, seconds + 0.5, 0.02)
    # start with the sine's phase at rest: a ramped amplitude avoids the velocity step at t = 0
    amp = 2 * np.pi / 9 * np.minimum(1.0, ts / 0.5)
    world.command_arm(0, ['arm_joint_2'], ts, (np.pi / 4 + amp * np.sin(np.pi / 2 * ts))[:, None])


def test_rest_is_equilibrium_and_ft_reads_the_arm_weight():
    with one_rover() as w:
        for _ in range(200):
            w.step()
        tr, s = w.truth(0), w.sense(0)
        assert np.abs(tr.dr).max() < 1e-5 and np.abs(tr.dtheta).max() < 1e-5
        np.testing.assert_allclose(s.force, [0, 0, (ARM_MASS + SENSOR_MASS) * 9.81], atol=1e-3)
        np.testing.assert_allclose(s.specific_force, [0, 0, 9.81], atol=1e-5)


def _arm_links(w: World) -> list[int]:
    ji = w.rovers[0].joint_index
    return [ji[n] for n in ('ft_sensor_joint', 'arm_joint_1', 'arm_joint_2', 'arm_joint_3',
                            'arm_joint_4')]


def _newton_euler_force(w: World, links, prev_v):
    m, _ = w.link_masses_and_coms(0, links)
    v = np.array([pb.getLinkState(w.rovers[0].body, j, computeLinkVelocity=1,
                                  physicsClientId=w.client)[6] for j in links])
    if prev_v is None:
        return None, v
    a = (v - prev_v) / w.dt
    return (m[:, None] * (a - np.array([0, 0, -9.81]))).sum(axis=0), v


def test_ft_equals_the_arms_newton_euler_reaction():
    """Eq. B-1: F_12 = m_2 (a_cm2 - g), from the arm links' own accelerations."""
    with one_rover() as w:
        excite(w, 3.0)
        links = _arm_links(w)
        prev, meas, ne = None, [], []
        for _ in range(500):
            w.step()
            f, prev = _newton_euler_force(w, links, prev)
            if f is not None:
                meas.append(w.sense(0).force)
                ne.append(f)
        meas, ne = np.array(meas), np.array(ne)
        signal = meas.std(axis=0)
        assert signal[0] > 0.05 and signal[2] > 0.05          # the arm really shakes the base
        rms = np.sqrt(((meas - ne) ** 2).mean(axis=0))
        assert np.all(rms[[0, 2]] < 0.1 * signal[[0, 2]]), (rms, signal)


def test_noisy_ft_differs_from_the_reaction_by_the_configured_noise():
    noise = NoiseConfig(fraction=0.1)
    with one_rover(noise=noise) as w:
        excite(w, 2.0)
        links = _arm_links(w)
        prev, diff = None, []
        for _ in range(400):
            w.step()
            f, prev = _newton_euler_force(w, links, prev)
            if f is not None:
                diff.append(w.sense(0).force - f)
        diff = np.array(diff)
        bound = noise.fraction * noise.force_n
        assert np.abs(diff.mean(axis=0)).max() < 0.2 * bound
        np.testing.assert_allclose(diff.std(axis=0), bound / np.sqrt(3), rtol=0.2)


def test_inclinometer_tilts_the_way_the_compliance_moves():
    soft = dataclasses.replace(load_truth(), stiffness=np.array([1e3, 1e3, 500, 250, 200, 3e3]))
    with one_rover(truth=soft) as w:
        readings = []
        for target in ([0.0, 0.0], [0.0, 1.2], [np.pi / 2, 0.0]):   # out front, up, to the left
            w.command_arm(0, ['arm_joint_1', 'arm_joint_2'], [1.5], [target])
            for _ in range(500):
                w.step()
            s, tr = w.sense(0), w.truth(0)
            truth_rp = matrix_to_rpy(tr.base_rotation)[:2]
            np.testing.assert_allclose(s.incl_angles, truth_rp, atol=40 / 1024 * np.pi / 180)
            np.testing.assert_allclose(truth_rp, tr.dtheta[:2], atol=1e-4)
            readings.append(s.incl_angles)
        front, up, left = readings
        # arm weight out front pitches the nose down (positive pitch about y, REP 103)
        assert front[1] - up[1] > 0.005
        # arm to the left rolls the base left-side down (negative roll about x)
        assert left[0] - up[0] < -0.005


def test_same_seed_same_world_and_readings():
    def run(seed):
        cfg = SimConfig(rovers=2, seed=seed, stereo_rate_hz=0.0)
        with World(cfg, [load_truth()] * 2) as w:
            w.command_arm(1, ['arm_joint_2'], [0.5], [[0.3]])
            w.command_velocity(0, 0.1, 0.2)
            out = []
            for _ in range(150):
                w.step()
                s = w.sense(1)
                out.append(np.concatenate([s.force, s.incl_angles, s.specific_force]))
            return w.layout, np.array(out)
    l1, a = run(7)
    l2, b = run(7)
    l3, c = run(8)
    assert l1 == l2 and l1 != l3
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_noise_scales_match_thesis_scenario():
    """The default max_sensed values are the dynamic ranges sensed under Eq. 2-21 (factor 2)."""
    with one_rover() as w:
        excite(w, 6.5)
        for _ in range(300):
            w.step()
        rows = []
        for _ in range(800):
            w.step()
            s = w.sense(0)
            rows.append(np.concatenate([s.specific_force, s.angular_velocity, s.force, s.torque]))
        r = np.array(rows)
        dev = np.abs(r - r.mean(axis=0)).max(axis=0)
        measured = {'accel_m_s2': dev[0:3].max(), 'gyro_rad_s': dev[3:6].max(),
                    'force_n': dev[6:9].max(), 'torque_nm': dev[9:12].max()}
        for name, value in measured.items():
            default = getattr(NoiseConfig(), name)
            assert 0.5 < value / default < 2.0, (name, value, default)


def test_stereo_pair_is_textured_and_offset_by_the_baseline():
    cfg = SimConfig(rovers=1, stereo_rate_hz=4.0, image_width=160, image_height=120)
    with World(cfg, [load_truth()]) as w:
        w.step()
        left, right = w.render_stereo(0)
        assert left.shape == (120, 160) and left.dtype == np.uint8
        assert left.std() > 10 and right.std() > 10
        assert not np.array_equal(left, right)
        k = w.intrinsics()
        assert k[0, 0] == pytest.approx(80 / np.tan(np.radians(41.2) / 2))
        p, r = w.camera_pose(0)
        assert np.allclose(r.T @ r, np.eye(3), atol=1e-9) and p[2] > 0.5


def test_supersampled_stereo_is_the_same_view_integrated_over_each_pixel():
    """supersample 3: the same camera (K unchanged, the same view), each pixel the mean of
    3 x 3 samples: close to the plain render, a little smoother."""
    cfg = SimConfig(rovers=1, stereo_rate_hz=4.0, image_width=160, image_height=120)
    with World(cfg, [load_truth()]) as a, World(cfg.replace(supersample=3), [load_truth()]) as b:
        a.step()
        b.step()
        assert np.array_equal(a.intrinsics(), b.intrinsics())
        pose = a.camera_pose(0)
        plain, smooth = a.render_stereo_at(*pose)[0], b.render_stereo_at(*pose)[0]
    assert smooth.shape == (120, 160) and smooth.dtype == np.uint8
    diff = np.abs(plain.astype(float) - smooth)
    assert np.median(diff) < 0.25 * plain.std()
    gradient = [np.abs(np.diff(img.astype(float), axis=1)).mean() for img in (plain, smooth)]
    assert gradient[1] < gradient[0]


def test_cmd_vel_moves_the_anchor_and_the_base_follows():
    with one_rover() as w:
        start = w.truth(0).base_position.copy()
        w.command_velocity(0, 0.2, 0.0)
        for _ in range(200):
            w.step()
        tr = w.truth(0)
        assert tr.anchor_position[0] - start[0] == pytest.approx(0.2, abs=1e-6)
        assert tr.base_position[0] - start[0] == pytest.approx(0.2, abs=0.01)
        xy, _, v, _ = w.odometry(0)
        assert v == pytest.approx(0.2) and xy[0] - start[0] == pytest.approx(0.2, abs=0.02)
        w.command_velocity(0, 5.0, 0.0)
        assert w.rovers[0].cmd[0] == pytest.approx(0.25)     # app. D top speed
        with pytest.raises(ValueError):
            w.command_velocity(0, float('nan'), 0.0)


def test_mismatched_truth_count_is_rejected():
    with pytest.raises(ValueError):
        World(SimConfig(rovers=2), [load_truth()])


def test_truth_vector_round_trip():
    t = load_truth()
    assert BaseParameters.from_vector(t.to_vector()).to_dict() == t.to_dict()


def test_sprung_body_has_exactly_the_true_mass_cg_and_inertia():
    """Base link + mast (everything the compliance holds, the arm excluded) = the truth YAML:
    mass, c.g. at the base frame origin, inertia tensor about it (Eq. 2-1's m_1, I_1), plus,
    in the engine, the h/2 lag term of its explicit rotational damper, B_rot h/2 (rover_model.
    base_link_inertial): the simulated body's effective inertia is the truth, which
    coop_id's test_sim_residual checks on the sensors."""
    truth = load_truth()
    with one_rover(truth=truth) as w:
        r, c = w.rovers[0], w.client
        parts = []
        com, orn = pb.getBasePositionAndOrientation(r.body, physicsClientId=c)
        info = pb.getDynamicsInfo(r.body, -1, physicsClientId=c)
        rot_com = np.array(pb.getMatrixFromQuaternion(orn)).reshape(3, 3)
        parts.append((info[0], np.array(com), rot_com, np.array(info[2])))
        for name in ('mast_pan', 'mast_tilt'):
            j = r.joint_index[name]
            st = pb.getLinkState(r.body, j, computeForwardKinematics=1, physicsClientId=c)
            info = pb.getDynamicsInfo(r.body, j, physicsClientId=c)
            parts.append((info[0], np.array(st[0]),
                          np.array(pb.getMatrixFromQuaternion(st[1])).reshape(3, 3),
                          np.array(info[2])))
        tr = w.truth(0)
        origin, rot = tr.base_position, tr.base_rotation
        mass = sum(p[0] for p in parts)
        cg = sum(p[0] * p[1] for p in parts) / mass
        inertia = np.zeros((3, 3))
        for m, pos, rr, diag in parts:
            d = pos - origin
            inertia += rr @ np.diag(diag) @ rr.T + m * (d @ d * np.eye(3) - np.outer(d, d))
        assert mass == pytest.approx(truth.mass, rel=1e-9)
        np.testing.assert_allclose(cg, origin, atol=1e-9)
        lag = 0.5 * w.substep_s * np.diag(truth.damping[3:])
        np.testing.assert_allclose(rot.T @ inertia @ rot, truth.inertia + lag, atol=1e-6)


def test_the_render_worker_draws_the_same_pair_and_is_replaced_when_it_dies():
    """render_workers 1: the right eye comes from a second process posed as this world is, the
    pair pixel for pixel the one-process pair; a worker killed mid-run leaves the simulator
    drawing both eyes itself, with render_note saying why."""
    pairs = {}
    for workers in (0, 1):
        cfg = SimConfig(rovers=2, noise=QUIET, image_width=160, image_height=120,
                        render_workers=workers)
        with World(cfg, [load_truth()] * 2) as w:
            w.command_velocity(0, 0.2, 0.3)
            w.command_arm(1, ['arm_joint_2'], [0.5], [[0.4]])
            w.command_mast(0, ['mast_pan'], [0.5], [[0.3]])
            for _ in range(120):
                w.step()
            pairs[workers] = [w.render_stereo(i) for i in (0, 1)]
            if workers:
                assert w.render_note is None
                w._render_worker._proc.kill()
                w._render_worker._proc.wait()
                again = w.render_stereo(0)
                assert 'render worker' in w.render_note
                np.testing.assert_array_equal(again[1], pairs[1][0][1])
    for (l0, r0), (l1, r1) in zip(pairs[0], pairs[1], strict=False):
        np.testing.assert_array_equal(l0, l1)
        np.testing.assert_array_equal(r0, r1)


def test_a_world_of_the_same_scene_keeps_the_render_worker_and_draws_as_a_fresh_one():
    """A reset to the same scene (the rovers placed anew) hands the render worker over to the
    new world; the pictures are those of a world given a worker of its own; a reset to another
    scene starts a new worker."""
    cfg = SimConfig(rovers=1, noise=QUIET, image_width=96, image_height=72, render_workers=1)
    truths = [load_truth()]
    w = World(cfg, truths)
    w.render_stereo(0)
    worker = w._render_worker
    assert w.hand_over_renderer(cfg.replace(slot_gap_m=0.12), truths) is None
    kept = w.hand_over_renderer(cfg, truths)
    assert kept is worker and w._render_worker is None
    w.close()                                   # the worker handed over outlives its world
    with World(cfg, truths, render_worker=kept) as again, World(cfg, truths) as fresh:
        for world in (again, fresh):
            world.place_rover(0, 0.5, 0.2, 0.3)
        pair, expected = again.render_stereo(0), fresh.render_stereo(0)
        assert again._render_worker is kept and again.render_note is None
        np.testing.assert_array_equal(pair[1], expected[1])


def test_a_render_worker_that_cannot_start_leaves_both_eyes_to_the_simulator(monkeypatch):
    import rover_sim.render_worker as rw
    monkeypatch.setattr(rw.sys, 'executable', '/nonexistent/python')
    cfg = SimConfig(rovers=1, noise=QUIET, image_width=64, image_height=48, render_workers=1)
    with World(cfg, [load_truth()]) as w:
        left, right = w.render_stereo(0)
        assert 'did not start' in w.render_note
        assert left.shape == right.shape == (48, 64) and left.std() > 0


def test_an_egl_renderer_that_cannot_load_leaves_the_pictures_to_tinyrenderer(monkeypatch):
    import importlib.util

    from rover_sim.config import ConfigError, Renderer
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, 'find_spec',
                        lambda name, *a: None if name == 'eglRenderer' else real(name, *a))
    cfg = SimConfig(rovers=1, noise=QUIET, image_width=64, image_height=48, renderer='egl')
    with World(cfg, [load_truth()]) as w:
        assert w.renderer is Renderer.TINY and 'TinyRenderer draws' in w.renderer_note
        left, _right = w.render_stereo(0)
        assert left.shape == (48, 64) and left.std() > 0
    with pytest.raises(ConfigError, match='renderer: must be one of tiny, egl'):
        SimConfig(renderer='opengl')


def test_a_heavier_load_weighs_on_the_sensor_and_the_true_zmp_is_the_cg_at_rest():
    """set_gripper_load: the F/T sensor carries the part's weight; mass_points: at rest the
    rover's particles put the zero-moment point (Eq. A-5) under their centre of mass."""
    from coop_insertion.tipover import Loads, zmp

    truth = load_truth()
    with World(SimConfig(rovers=2, seed=1, stereo_rate_hz=0.0,
                         noise=NoiseConfig(fraction=0.0)), [truth, truth]) as w:
        for _ in range(100):
            w.step()
        before = w.sense(1).force[2]
        w.set_gripper_load(1, 0.5)
        for _ in range(800):            # the base sinks on its overdamped heave (tau ~0.6 s)
            w.step()
        assert w.sense(1).force[2] - before == pytest.approx(0.49 * 9.81, abs=0.05)
        m, c, v = w.mass_points(1)
        assert m.sum() == pytest.approx(truth.mass + 1.0 + 0.5 + 1e-3, abs=1e-6)
        w.step()
        m, c, v2 = w.mass_points(1)
        p = zmp(Loads.of(m, c, (v2 - v) / w.dt))
        assert p == pytest.approx((m @ c / m.sum())[:2], abs=1e-3)
        with pytest.raises(ValueError):
            w.set_gripper_load(0, 0.5)                     # rover 1 holds nothing


def _ignores_sigint(pid: int) -> bool:
    """Whether process `pid` ignores SIGINT now (the SigIgn mask in /proc/<pid>/status)."""
    try:
        status = Path(f'/proc/{pid}/status').read_text()
    except OSError:
        return False
    mask = next((line.split()[1] for line in status.splitlines()
                 if line.startswith('SigIgn:')), '0')
    return bool(int(mask, 16) & (1 << (signal.SIGINT - 1)))


def test_a_render_worker_outlives_a_ctrl_c_while_it_starts_and_ends_quietly():
    """A Ctrl-C to the simulator's process group can come while the worker is still importing:
    it is ignored from the first line, and the simulator ending before it sent the scene ends
    the worker without a traceback."""
    proc = subprocess.Popen([sys.executable, '-c', _START], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        # the signal once the worker's first statement has run (its SigIgn mask shows SIGINT),
        # while it goes on to import numpy and PyBullet; a loaded host may take a while
        deadline = time.monotonic() + 30.0
        while not _ignores_sigint(proc.pid) and proc.poll() is None:
            assert time.monotonic() < deadline, 'the worker never ignored SIGINT'
            time.sleep(0.005)
        proc.send_signal(signal.SIGINT)
        time.sleep(0.5)
        assert proc.poll() is None
        proc.stdin.close()
        proc.wait(timeout=30)
        err = proc.stderr.read()
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == 0 and b'Traceback' not in err, err.decode()[-2000:]
