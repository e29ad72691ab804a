"""The thesis rover's kinematic geometry (app. D, Fig. 2-2): the 4-DOF arm on its F/T sensor with
the card in its gripper, and the pan/tilt stereo mast. One place for the numbers the simulator
builds its URDF from and the nodes that reason about a real or simulated rover use: the card's
pose in the base frame from the arm's encoders (`card_in_base`), the arm's inverse (`card_ik`),
the left camera's pose from the mast's (`camera_in_base`). No rclpy, no pybullet.

Base frame (`<rover>/base_link`, REP 103): at the base's c.g., x forward, z up. The F/T sensor
(the arm's base) sits at r_2 (the identified c.g. offset, coop_common.dynparams); arm joint 1
turns about z above it, joints 2..4 pitch about their y axes in the arm's plane.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from .errors import CoopCommonError

#: the base's c.g. above flat ground at rest (the odometry frame's z = 0 is the ground)
BASE_HEIGHT_M = 0.30

#: skid-steer track (m) and the wheelbase (m): the four wheels' ground contacts, base frame
#: (x forward, y left, on the ground BASE_HEIGHT_M below the c.g.), span the support polygon
#: the zero-moment point must stay in (app. A.3)
TRACK_M = 0.30
WHEELBASE_M = 0.40
WHEEL_CONTACTS = np.array([[sx * WHEELBASE_M / 2, sy * TRACK_M / 2, -BASE_HEIGHT_M]
                           for sx in (1, -1) for sy in (1, -1)])

ARM_JOINTS = ('arm_joint_1', 'arm_joint_2', 'arm_joint_3', 'arm_joint_4')
MAST_JOINTS = ('mast_pan', 'mast_tilt')
#: the joint groups a rover takes trajectories for, each on its own command topic
#: (`<rover>/arm/joint_command`, `<rover>/mast/command`), and their joints
JointGroup = Literal['arm', 'mast']
GROUP_JOINTS: dict[JointGroup, tuple[str, ...]] = {'arm': ARM_JOINTS, 'mast': MAST_JOINTS}


@dataclass(frozen=True)
class ArmLink:
    """One arm link's mass properties and length (link frame, SI units)."""

    name: str
    mass: float
    com: tuple[float, float, float]
    inertia: tuple[float, float, float]     # principal, about the link's c.o.m., link axes
    length: float                           # where the next joint sits along the link's x (m)


#: Arm of §2.6.1: 1 kg in all; link 2 carries most of it so the arm as a whole has inertias close
#: to the thesis's I_x = I_z = 0.02, I_y = 0.001 kg m^2 when stretched out.
ARM_LINKS = (
    ArmLink('arm_link_1', 0.15, (0.0, 0.0, 0.03), (2e-4, 2e-4, 1e-4), 0.06),
    ArmLink('arm_link_2', 0.45, (0.125, 0.0, 0.0), (1e-4, 2.4e-3, 2.4e-3), 0.25),
    ArmLink('arm_link_3', 0.30, (0.10, 0.0, 0.0), (5e-5, 1.0e-3, 1.0e-3), 0.20),
    ArmLink('arm_link_4', 0.10, (0.04, 0.0, 0.0), (1e-5, 6e-5, 6e-5), 0.08),
)
ARM_MASS = sum(link.mass for link in ARM_LINKS)
ARM_LIMITS_RAD = ((-np.pi, np.pi), (-2.0, 2.0), (-2.5, 2.5), (-2.0, 2.0))
MAST_POSITION = (-0.12, -0.10, 0.40)      # pan joint, relative to the base c.g. (m)
CAMERA_OFFSET = (0.04, 0.0, 0.06)          # left optical origin, in the tilt link
STEREO_BASELINE_M = 0.038
#: the card's centre in the last arm link (x along the link): its near edge at the gripper
CARD_OFFSET_M = 0.134
#: arm joint 1 sits this far above the F/T sensor's origin, joint 2 this far above joint 1
ARM_JOINT1_ABOVE_SENSOR_M = 0.015
#: the mast's tilt joint sits this far above its pan joint
TILT_ABOVE_PAN_M = 0.04
MAST_TILT_LIMITS_RAD = (-1.2, 1.2)
#: r_2 as designed: the arm mount from the base c.g. (m); each rover's own is identified (coop_id)
NOMINAL_CG_TO_ARM = (0.0, 0.3, 0.1)
OPTICAL_IN_TILT = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


class ReachError(CoopCommonError):
    """A card pose the arm cannot reach."""


def card_ik(x: float, z: float, pitch: float = 0.0) -> tuple[float, float, float]:
    """Arm joints 2..4 that put the card's centre at (x, z) from joint 2's axis in the arm's
    plane (x along joint 1's heading, z up) with the card pitched by `pitch` (rad, about the
    joint axes: positive tilts its width axis down); the elbow above the line from joint 2 to
    joint 4 where the joint limits allow, else below. ReachError when out of reach."""
    l2, l3 = ARM_LINKS[1].length, ARM_LINKS[2].length
    l4 = CARD_OFFSET_M
    # joint 4 = card centre less the card's offset along the pitched link 4
    wx, wz = x - l4 * np.cos(pitch), z + l4 * np.sin(pitch)
    r2 = wx * wx + wz * wz
    c3 = (r2 - l2 * l2 - l3 * l3) / (2.0 * l2 * l3)
    if not (np.isfinite(c3) and -1.0 <= c3 <= 1.0):
        raise ReachError(f'card at ({x:.3f}, {z:.3f}) m, pitch {pitch:.3f} is out of reach')
    why = ''
    for q3 in (float(np.arccos(c3)), -float(np.arccos(c3))):     # elbow up first, then down
        q2 = float(np.arctan2(-wz, wx) - np.arctan2(l3 * np.sin(q3), l2 + l3 * np.cos(q3)))
        q = (q2, q3, float(pitch - q2 - q3))
        bad = [(k + 2, v) for k, v in enumerate(q)
               if not ARM_LIMITS_RAD[k + 1][0] <= v <= ARM_LIMITS_RAD[k + 1][1]]
        if not bad:
            return q
        why = ', '.join(f'arm_joint_{k} = {v:.3f} rad' for k, v in bad)
    raise ReachError(f'card at ({x:.3f}, {z:.3f}) m, pitch {pitch:.3f}: {why} beyond its limits')


def card_fk(q2: float, q3: float, q4: float) -> tuple[float, float, float]:
    """The card's centre (x, z) from joint 2's axis and its pitch: card_ik's inverse."""
    l2, l3 = ARM_LINKS[1].length, ARM_LINKS[2].length
    t2, t3, t4 = q2, q2 + q3, q2 + q3 + q4
    x = l2 * np.cos(t2) + l3 * np.cos(t3) + CARD_OFFSET_M * np.cos(t4)
    z = -(l2 * np.sin(t2) + l3 * np.sin(t3) + CARD_OFFSET_M * np.sin(t4))
    return float(x), float(z), float(t4)




def arm_gravity_moment(q: Sequence[float] | np.ndarray, *, g: float = 9.81) -> np.ndarray:
    """The moment of the arm's own weight (ARM_LINKS beyond the F/T sensor) that the sensor
    reads at joint angles q (4, rad): base axes, about the sensor's origin, the base level.
    Quasi-static (no link accelerations). The force part is the arm's weight whatever q is; the
    moment moves with the links' centres of mass: mg (a_y, -a_x, 0) summed, a the centre's
    horizontal offset from the sensor."""
    q1, q2, q3, q4 = (float(v) for v in q)
    l2, l3 = ARM_LINKS[1].length, ARM_LINKS[2].length
    t2, t3, t4 = q2, q2 + q3, q2 + q3 + q4
    # each link's c.o.m. along the arm's plane, from joint 1's vertical axis
    reach = (ARM_LINKS[0].com[0],
             ARM_LINKS[1].com[0] * np.cos(t2),
             l2 * np.cos(t2) + ARM_LINKS[2].com[0] * np.cos(t3),
             l2 * np.cos(t2) + l3 * np.cos(t3) + ARM_LINKS[3].com[0] * np.cos(t4))
    first = sum(link.mass * x for link, x in zip(ARM_LINKS, reach, strict=False))
    return np.array([g * first * np.sin(q1), -g * first * np.cos(q1), 0.0])


def yaw_of(qx: float, qy: float, qz: float, qw: float) -> float:
    """Heading (rad) of a quaternion (x, y, z, w): its rotation about z (e.g. odometry's)."""
    return float(np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz)))


def camera_in_map(x: float, y: float, yaw: float, pan: float, tilt: float) -> np.ndarray:
    """4x4 pose of the left optical frame in the map (odometry) frame of a rover standing at
    (x, y) with heading yaw on flat ground (its c.g. BASE_HEIGHT_M up), mast at pan and tilt."""
    base = np.eye(4)
    base[:3, :3] = _rot_z(yaw)
    base[:3, 3] = (x, y, BASE_HEIGHT_M)
    return base @ camera_in_base(pan, tilt)


def mast_aim(x: float, y: float, yaw: float, target: Sequence[float] | np.ndarray
             ) -> tuple[float, float]:
    """The mast's pan and tilt (rad) that put the map point `target` on the left camera's
    optical axis for a rover standing at (x, y) with heading yaw (camera_in_map's rover). The
    camera moves with the joints, so the angles are refined until they point at the target
    from where they put the camera. ReachError when the target lies within the mast's own
    reach or the tilt it needs is beyond the joint's limits."""
    base = np.eye(4)
    base[:3, :3] = _rot_z(yaw)
    base[:3, 3] = (x, y, BASE_HEIGHT_M)
    local = (np.linalg.inv(base) @ np.append(np.asarray(target, float), 1.0))[:3]
    if not np.all(np.isfinite(local)):
        raise ReachError(f'target {np.asarray(target).tolist()} is not a finite point')
    pan = tilt = 0.0
    for _ in range(20):
        v = local - camera_in_base(pan, tilt)[:3, 3]
        if np.linalg.norm(v) < 0.1:
            raise ReachError(f'target {np.round(np.asarray(target, float), 3).tolist()} lies '
                             "within the mast's reach")
        new = (float(np.arctan2(v[1], v[0])), float(np.arctan2(-v[2], np.hypot(v[0], v[1]))))
        done = max(abs(new[0] - pan), abs(new[1] - tilt)) < 1e-9
        pan, tilt = new
        if done:
            break
    lo, hi = MAST_TILT_LIMITS_RAD
    if not lo <= tilt <= hi:
        raise ReachError(f'tilt {tilt:.3f} rad is beyond the mast tilt limits [{lo}, {hi}]')
    return pan, tilt


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def joint2_in_base(cg_to_arm: Sequence[float] | np.ndarray) -> np.ndarray:
    """Arm joint 2's axis point in the base frame at joint 1 = 0 (joint 1 turns about the
    vertical through it): r_2 plus the heights of joint 1 and of joint 2 above it."""
    r2 = np.asarray(cg_to_arm, float)
    return r2 + np.array([0.0, 0.0, ARM_JOINT1_ABOVE_SENSOR_M + ARM_LINKS[0].length])


def card_in_base(q: Sequence[float] | np.ndarray, cg_to_arm: Sequence[float] | np.ndarray
                 ) -> np.ndarray:
    """4x4 pose of the card frame (centre; x along its width, y its face normal, z its height)
    in the base frame from the arm's four joint angles and r_2."""
    q1, q2, q3, q4 = (float(v) for v in q)
    x, z, pitch = card_fk(q2, q3, q4)
    rz = _rot_z(q1)
    t = np.eye(4)
    t[:3, :3] = rz @ _rot_y(pitch)
    t[:3, 3] = joint2_in_base(cg_to_arm) + rz @ np.array([x, 0.0, z])
    return t


def card_joints(position: Sequence[float] | np.ndarray, heading: float, pitch: float,
                cg_to_arm: Sequence[float] | np.ndarray) -> tuple[float, float, float, float]:
    """Arm joints that put the card's centre at `position` (base frame) with joint 1 at
    `heading` (rad about z: the card's width axis then points along it) and pitched by `pitch`;
    the centre must lie in the plane joint 1 turns the arm into. ReachError otherwise."""
    p = np.asarray(position, float) - joint2_in_base(cg_to_arm)
    local = _rot_z(heading).T @ p
    if abs(local[1]) > 1e-6:
        raise ReachError(f'card centre {local[1]:.4f} m off the arm plane at heading '
                         f'{heading:.3f}')
    return (float(heading), *card_ik(float(local[0]), float(local[2]), pitch))


def camera_in_base(pan: float, tilt: float) -> np.ndarray:
    """4x4 pose of the left optical frame (z forward, x right, y down) in the base frame from
    the mast's pan and tilt (rad; positive tilt looks down)."""
    rz = _rot_z(pan)
    ry = _rot_y(tilt)
    t = np.eye(4)
    t[:3, :3] = rz @ ry @ OPTICAL_IN_TILT
    t[:3, 3] = np.asarray(MAST_POSITION) + rz @ (np.array([0.0, 0.0, TILT_ABOVE_PAN_M]) +
                                                ry @ np.asarray(CAMERA_OFFSET))
    return t


#: the farthest the left camera stands from the base c.g. across the ground, at any tilt (m):
#: a view's camera and the rover that takes it are at most this far apart
CAMERA_FROM_BASE_M = float(max(np.hypot(*camera_in_base(0.0, t)[:2, 3])
                               for t in np.linspace(*MAST_TILT_LIMITS_RAD, 241)))


@dataclass(frozen=True)
class CameraMount:
    """Where a rover stands and how it turns its mast to put its left camera at a pose: base
    c.g. (x, y) and heading, pan and tilt (rad), and the camera height that gives (m)."""

    base_xy: tuple[float, float]
    base_yaw: float
    pan: float
    tilt: float
    camera_z: float


def camera_mount(camera_xy: tuple[float, float], yaw: float, pitch: float, *,
                 base_z: float = 0.30) -> CameraMount:
    """The rover pose and mast angles that put the left optical frame at `camera_xy` looking
    along heading `yaw` and `pitch` (rad, positive down, coop_viewplan's convention): the base
    faces the view (pan 0) and the tilt takes the pitch; the camera's height follows from the
    mast (`camera_z`). ReachError when the tilt is beyond the joint's limits."""
    lo, hi = MAST_TILT_LIMITS_RAD
    if not lo <= pitch <= hi:
        raise ReachError(f'pitch {pitch:.3f} rad is beyond the mast tilt limits [{lo}, {hi}]')
    cy, sy = np.cos(yaw), np.sin(yaw)
    ct, st = np.cos(pitch), np.sin(pitch)
    cx, _, cz = CAMERA_OFFSET
    # the camera in the base frame: pan joint, tilt joint above it, offset in the tilted link
    local = np.array([MAST_POSITION[0] + ct * cx + st * cz, MAST_POSITION[1],
                      MAST_POSITION[2] + TILT_ABOVE_PAN_M - st * cx + ct * cz])
    world_off = np.array([cy * local[0] - sy * local[1], sy * local[0] + cy * local[1]])
    return CameraMount((float(camera_xy[0] - world_off[0]), float(camera_xy[1] - world_off[1])),
                       float(yaw), 0.0, float(pitch), float(base_z + local[2]))
