"""The servo-rate core against a simulated slave: skid-steer base whose wheel odometry drifts,
an arm that moves the card, vision at 2-5 Hz with latency and noise, servo at 50-100 Hz."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coop_insertion.errors import InsertionError
from coop_insertion.frames import homogeneous, rot_z
from coop_insertion.servo import VisionFix, VisualServo


class Plant:
    """World truth and what the slave believes. The base moves 4 % further and turns 5 % more
    than commanded, plus a 0.005 rad/s yaw drift while driving (slip): its odometry integrates
    the commands. The arm moves the card 3 % less than commanded."""

    def __init__(self, rng: np.random.Generator, *, arm_gain: float = 0.97):
        self.rng = rng
        self.base_w = np.array([0.0, 0.0, 0.0])          # x, y, yaw (world)
        self.base_o = np.array([0.0, 0.0, 0.0])          # odometry's belief (odom frame)
        self.card_b = homogeneous(rot_z(0.25), [0.30, 0.08, 0.22])
        self.arm_gain = arm_gain
        self.goal_w = homogeneous(rot_z(0.05), [1.10, -0.12, 0.28])

    @staticmethod
    def _pose(x: np.ndarray) -> np.ndarray:
        return homogeneous(rot_z(x[2]), [x[0], x[1], 0.0])

    def step(self, cmd, dt: float) -> None:
        v, w = cmd.base_linear_x, cmd.base_angular_z
        for state, scale, bias in ((self.base_w, (1.04, 1.05), 0.005),
                                   (self.base_o, (1, 1), 0.0)):
            state[0] += scale[0] * v * np.cos(state[2]) * dt
            state[1] += scale[0] * v * np.sin(state[2]) * dt
            state[2] += (scale[1] * w + (bias if abs(v) > 1e-3 else 0.0)) * dt
        self.card_b[:3, 3] += self.arm_gain * cmd.arm_linear * dt
        self.card_b[:3, :3] = (Rotation.from_rotvec(self.arm_gain * cmd.arm_angular * dt)
                               .as_matrix() @ self.card_b[:3, :3])

    def card_w(self) -> np.ndarray:
        return self._pose(self.base_w) @ self.card_b

    def odometry(self) -> tuple[np.ndarray, np.ndarray]:
        return self._pose(self.base_o), self.card_b.copy()

    def vision(self, stamp: float, sigma_m: float, sigma_rad: float) -> VisionFix:
        """Eq. 5-4 in the true base frame, with noise (what the master measures)."""
        r_wb = self._pose(self.base_w)[:3, :3]
        card = self.card_w()
        t = r_wb.T @ (self.goal_w[:3, 3] - card[:3, 3])
        rv = r_wb.T @ Rotation.from_matrix(self.goal_w[:3, :3] @ card[:3, :3].T).as_rotvec()
        cov = np.diag([sigma_m ** 2] * 3 + [sigma_rad ** 2] * 3)
        return VisionFix(stamp, t + self.rng.normal(0, sigma_m, 3),
                         rv + self.rng.normal(0, sigma_rad, 3), cov,
                         approach_axis=r_wb.T @ self.goal_w[:3, 0])

    def error(self) -> tuple[float, float]:
        c = self.card_w()
        return (float(np.linalg.norm(self.goal_w[:3, 3] - c[:3, 3])),
                float(np.linalg.norm(Rotation.from_matrix(self.goal_w[:3, :3] @ c[:3, :3].T)
                                     .as_rotvec())))

    def along_past_goal(self) -> float:
        """How far the card is past the goal along the approach axis (goal's x)."""
        return float(self.goal_w[:3, 0] @ (self.card_w()[:3, 3] - self.goal_w[:3, 3]))


def run(servo: VisualServo, *, vision_hz: float, servo_hz: float, latency_s: float,
        duration_s: float, seed: int = 0, vision_until_s: float = np.inf,
        sigma_m: float = 0.0005, sigma_rad: float = 0.003, fix_sigma_m: float | None = None):
    rng = np.random.default_rng(seed)
    plant = Plant(rng)
    dt = 1.0 / servo_hz
    pending: list[tuple[float, VisionFix]] = []
    next_image = 0.0
    log = []
    for k in range(round(duration_s * servo_hz)):
        t = k * dt
        servo.add_odometry(t, *plant.odometry())
        if t + 1e-9 >= next_image:
            if t < vision_until_s:
                fix = plant.vision(t, sigma_m, sigma_rad)
                if fix_sigma_m is not None:
                    fix = VisionFix(fix.stamp, fix.translation, fix.rotvec,
                                    np.diag([fix_sigma_m ** 2] * 3 + [sigma_rad ** 2] * 3),
                                    fix.approach_axis)
                pending.append((t + latency_s, fix))
            next_image += 1.0 / vision_hz
        while pending and pending[0][0] <= t + 1e-9:
            servo.add_vision(pending.pop(0)[1])
        cmd = servo.command(t)
        plant.step(cmd, dt)
        log.append((t, *plant.error(), plant.along_past_goal(), cmd))
    return plant, log


@pytest.mark.parametrize('vision_hz,servo_hz', [(2.0, 50.0), (2.0, 100.0), (5.0, 50.0),
                                                (5.0, 100.0)])
def test_converges_with_slow_late_vision(vision_hz, servo_hz):
    plant, log = run(VisualServo(), vision_hz=vision_hz, servo_hz=servo_hz, latency_s=0.3,
                     duration_s=25.0, seed=int(vision_hz * servo_hz))
    start = log[0][1]
    err, ang = plant.error()
    assert start > 0.5
    assert err < 0.002, err                      # 2 mm, with 0.5 mm vision noise
    assert ang < 0.01, ang
    # never past the goal along the approach axis by more than the noise
    assert max(row[3] for row in log) < 0.002
    # the base did part of the work (the goal was out of the arm's reach)
    assert any(abs(row[4].base_linear_x) > 0.05 for row in log)
    # bounded
    srv = VisualServo()
    for row in log:
        cmd = row[4]
        assert abs(cmd.base_linear_x) <= srv.max_base_speed + 1e-12
        assert np.linalg.norm(cmd.arm_linear) <= srv.max_arm_speed + 1e-12
        assert np.linalg.norm(cmd.arm_angular) <= srv.max_arm_rate + 1e-12


def test_prediction_between_fixes_is_what_closes_the_loop():
    """Using each fix as the current error until the next one (no odometry prediction) with the
    same gains oscillates or stalls far from the goal; the predicted error converges."""
    plant, _ = run(VisualServo(), vision_hz=2.0, servo_hz=50.0, latency_s=0.3, duration_s=20.0)
    good = plant.error()[0]

    class Naive(VisualServo):
        def add_odometry(self, t, t_odom_base, t_base_card):
            super().add_odometry(t, np.eye(4) if self._hist else t_odom_base,
                                 t_base_card if not self._hist else self._hist[0][2])

    plant_n, _ = run(Naive(), vision_hz=2.0, servo_hz=50.0, latency_s=0.3, duration_s=20.0)
    assert plant_n.error()[0] > 10 * good


def test_holds_when_vision_is_lost():
    servo = VisualServo(vision_timeout_s=0.8)
    _plant, log = run(servo, vision_hz=4.0, servo_hz=100.0, latency_s=0.2, duration_s=10.0,
                     vision_until_s=3.0)
    # the newest fix was taken before 3.0 s and arrived 0.2 s later: held from ~3.8 s on
    held = [row for row in log if row[0] > 3.8]
    assert all(row[4].held and 'vision lost' in row[4].reason for row in held)
    assert all(row[4].base_linear_x == 0.0 and row[4].base_angular_z == 0.0 and
               not np.any(row[4].arm_linear) and not np.any(row[4].arm_angular)
               for row in held)
    # the card did not move while held
    assert abs(held[0][1] - held[-1][1]) < 1e-12
    # and before that it was moving
    assert not log[150][4].held


def test_no_vision_no_motion():
    servo = VisualServo()
    servo.add_odometry(0.0, np.eye(4), np.eye(4))
    cmd = servo.command(0.0)
    assert cmd.held and cmd.reason == 'no vision yet'
    assert VisualServo().command(0.0).reason == 'no odometry'


def test_never_drives_into_contact_blind():
    """The goal is a pre-insertion pose standoff_m in front of the contact plane (along the
    approach axis). The card is commanded forward only while it stays n_sigma goal sigmas clear
    of the plane: with a goal sigma of 15 mm along the axis and a 5 mm stand-off it is not
    driven forward at all (3 sigma = 45 mm beyond the plane 35 mm ahead; sideways alignment goes
    on); with 0.5 mm it is driven to the goal."""
    def first_command(sigma_along: float, standoff: float = 0.005):
        servo = VisualServo(standoff_m=standoff, n_sigma=3.0, base_deadband_m=1.0)
        card_b = homogeneous(np.eye(3), [0.35, 0.0, 0.25])
        servo.add_odometry(0.0, np.eye(4), card_b)
        cov = np.diag([sigma_along ** 2, 1e-8, 1e-8, 1e-6, 1e-6, 1e-6])
        servo.add_vision(VisionFix(0.0, [0.03, 0.01, 0.0], np.zeros(3), cov,
                                   approach_axis=[1.0, 0.0, 0.0]))
        return servo.command(0.05)

    blind = first_command(0.015)
    assert blind.arm_linear[0] <= 0.0 and blind.base_linear_x == 0.0
    assert blind.arm_linear[1] > 0.0                 # still aligning sideways
    assert 'approach limited' in blind.reason
    sure = first_command(0.0005)
    assert sure.arm_linear[0] > 0.0 and sure.reason == 'servo'
    # in between: forward only up to the plane minus 3 sigma
    part = first_command(0.004, standoff=0.02)       # room 0.03 + 0.02 - 0.012 = 0.038
    assert np.isclose(part.error_translation[0], 0.03)
    part = first_command(0.01, standoff=0.02)        # room 0.03 + 0.02 - 0.03 = 0.02
    assert np.isclose(part.error_translation[0], 0.02)
    # and in the closed loop the card never passes the contact plane
    plant, log = run(VisualServo(standoff_m=0.005), vision_hz=4.0, servo_hz=50.0,
                     latency_s=0.2, duration_s=25.0)
    assert plant.error()[0] < 0.002
    assert max(row[3] for row in log) < 0.005


def test_late_fix_uses_odometry_at_its_stamp():
    """A fix stamped while the base was elsewhere gives the same goal as one taken now."""
    servo = VisualServo()
    card_b = homogeneous(np.eye(3), [0.3, 0.0, 0.2])
    goal_odom = np.array([1.0, 0.2, 0.2])
    for k in range(11):
        t = 0.1 * k
        base = homogeneous(rot_z(0.05 * k), [0.05 * k, 0.0, 0.0])
        servo.add_odometry(t, base, card_b)
    base_then = homogeneous(rot_z(0.05 * 3), [0.15, 0.0, 0.0])
    card_then = base_then @ card_b
    trans = base_then[:3, :3].T @ (goal_odom - card_then[:3, 3])
    servo.add_vision(VisionFix(0.3, trans, np.zeros(3), np.eye(6) * 1e-6))
    base_now = homogeneous(rot_z(0.5), [0.5, 0.0, 0.0])
    cmd = servo.command(1.0)
    expect = base_now[:3, :3].T @ (goal_odom - (base_now @ card_b)[:3, 3])
    assert np.allclose(cmd.error_translation, expect, atol=1e-9)
    with pytest.raises(InsertionError):
        servo.add_vision(VisionFix(-5.0, trans, np.zeros(3), np.eye(6) * 1e-6))


def test_bad_input_raises():
    with pytest.raises(InsertionError):
        VisualServo(max_arm_speed_m_s=0.0)
    with pytest.raises(InsertionError):
        VisionFix(0.0, [0, 0, np.nan], np.zeros(3), np.eye(6))
    with pytest.raises(InsertionError):
        VisionFix(0.0, np.zeros(3), np.zeros(3), -np.eye(6))
    servo = VisualServo()
    servo.add_odometry(1.0, np.eye(4), np.eye(4))
    with pytest.raises(InsertionError):
        servo.add_odometry(0.5, np.eye(4), np.eye(4))
    with pytest.raises(InsertionError):
        servo.add_odometry(2.0, np.full((4, 4), np.nan), np.eye(4))
