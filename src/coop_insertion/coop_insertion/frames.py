"""Relating the cooperating robots' frames (Sujan 2002, §5.1, Fig. 5-4, Eq. 5-1..5-4).

A target's frame is fixed by three non-collinear points measured in the vision frame R_V:
P1 the origin, P2 on the frame's x axis and P3 on its z axis (the axes Eq. 5-1 reads: R_z and
R_y are the heading and elevation of P1-P2, R_x the lean of P1-P3). Eq. 5-2 composes the
rotation as R^x . R^y . R^z, so a frame's Euler angles here are (R_x, R_y, R_z) with
R = Rx(R_x) @ Ry(R_y) @ Rz(R_z).

Naming (the thesis's): A_VT is the pose of the slave's end-effector (object, card) frame R_T in
the vision frame R_V (it maps T coordinates to V coordinates), A_VO the goal's (insertion site's)
frame in R_V, A_TS the end-effector frame in the slave's arm-base frame R_S, from the arm
kinematics. A_TS must be the pose of the same frame the card's markers define (the arm kinematics
composed with the fixed card-on-gripper offset). All transforms are 4x4 homogeneous numpy arrays.

Eq. 5-1 as printed is a decoupled small-angle reading: each angle is taken from one pair of points
in camera coordinates, without undoing the others, and R_y uses the difference of the points'
horizontal ranges from the camera instead of their horizontal separation. `euler_eq_5_1` is that
literal formula; `frame_from_points` + `euler_from_rotation` is the exact frame through the same
three points (what the transforms below use). They agree for a rotation about one axis (R_x or
R_z alone, and R_y alone when P2 lies radially towards the camera's vertical axis from P1).

No rclpy here.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from .errors import InsertionError

__all__ = [
    'RequiredMotion',
    'a_ts',
    'a_vt',
    'euler_eq_5_1',
    'euler_from_rotation',
    'frame_from_points',
    'homogeneous',
    'invert',
    'required_motion',
    'required_motion_from_points',
    'rot_x',
    'rot_y',
    'rot_z',
    'rotation_from_euler',
    'third_point',
]

#: Below this sine of the angle P2-P1-P3 (or length ratio) the three points count as collinear.
COLLINEAR_SINE = 1e-3


def _vec3(name: str, v: ArrayLike) -> np.ndarray:
    a = np.asarray(v, float)
    if a.shape != (3,):
        raise InsertionError(f'{name} must be a 3-vector, got shape {a.shape}')
    if not np.all(np.isfinite(a)):
        raise InsertionError(f'{name} must be finite, got {a}')
    return a


def _transform(name: str, t: ArrayLike) -> np.ndarray:
    a = np.asarray(t, float)
    if a.shape != (4, 4):
        raise InsertionError(f'{name} must be a 4x4 homogeneous transform, got {a.shape}')
    if not np.all(np.isfinite(a)):
        raise InsertionError(f'{name} must be finite')
    if not np.allclose(a[3], [0, 0, 0, 1], atol=1e-9):
        raise InsertionError(f'{name}: last row must be [0, 0, 0, 1], got {a[3]}')
    r = a[:3, :3]
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise InsertionError(f'{name}: rotation block is not a proper rotation')
    return a


def rot_x(a: float) -> np.ndarray:
    """Rotation matrix about x by a (rad): R^x of Eq. 5-2."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """Rotation matrix about y by a (rad): R^y of Eq. 5-2."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    """Rotation matrix about z by a (rad): R^z of Eq. 5-2."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_from_euler(angles: ArrayLike) -> np.ndarray:
    """Eq. 5-2's rotation block R^x . R^y . R^z from (R_x, R_y, R_z) in rad."""
    rx, ry, rz = _vec3('angles', angles)
    return rot_x(rx) @ rot_y(ry) @ rot_z(rz)


def euler_from_rotation(r: ArrayLike) -> np.ndarray:
    """(R_x, R_y, R_z) with r = Rx @ Ry @ Rz (Eq. 5-2's order), R_y in [-pi/2, pi/2].

    At R_y = +-pi/2 (gimbal lock) R_x and R_z are not separable; R_x is then returned as 0."""
    m = np.asarray(r, float)
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        raise InsertionError('rotation must be a finite 3x3 matrix')
    if not np.allclose(m.T @ m, np.eye(3), atol=1e-6) or np.linalg.det(m) < 0:
        raise InsertionError('not a proper rotation matrix')
    sy = float(np.clip(m[0, 2], -1.0, 1.0))
    ry = float(np.arcsin(sy))
    if abs(sy) > 1.0 - 1e-12:
        return np.array([0.0, ry, float(np.arctan2(m[1, 0], m[1, 1]))])
    return np.array([float(np.arctan2(-m[1, 2], m[2, 2])), ry,
                     float(np.arctan2(-m[0, 1], m[0, 0]))])


def _check_triangle(p1: np.ndarray, p2: np.ndarray, p3: np.ndarray) -> None:
    a, b = p2 - p1, p3 - p1
    la, lb = np.linalg.norm(a), np.linalg.norm(b)
    if la == 0.0 or lb == 0.0:
        raise InsertionError('frame points coincide (P2 or P3 equals P1)')
    if np.linalg.norm(np.cross(a, b)) / (la * lb) < COLLINEAR_SINE:
        raise InsertionError('frame points are collinear: three points fix no frame')


def euler_eq_5_1(p1: ArrayLike, p2: ArrayLike, p3: ArrayLike) -> np.ndarray:
    """Eq. 5-1 as printed: (R_x, R_y, R_z) of the frame (P1 origin, P2 on x, P3 on z) in the
    camera frame, each from one pair of points (decoupled, small-angle; see the module notes).

        R_z = atan((P1y - P2y) / (P1x - P2x))
        R_y = atan((P1z - P2z) / (sqrt(P1x^2 + P1y^2) - sqrt(P2x^2 + P2y^2)))
        R_x = atan((P3y - P1y) / (P1z - P3z))

    arctan, not arctan2, as printed: each angle is in (-pi/2, pi/2]."""
    p1, p2, p3 = _vec3('P1', p1), _vec3('P2', p2), _vec3('P3', p3)
    _check_triangle(p1, p2, p3)

    def atan_ratio(num: float, den: float) -> float:
        if den == 0.0:
            return float(np.copysign(np.pi / 2, num)) if num != 0.0 else 0.0
        return float(np.arctan(num / den))

    rz = atan_ratio(p1[1] - p2[1], p1[0] - p2[0])
    ry = atan_ratio(p1[2] - p2[2], np.hypot(p1[0], p1[1]) - np.hypot(p2[0], p2[1]))
    rx = atan_ratio(p3[1] - p1[1], p1[2] - p3[2])
    return np.array([rx, ry, rz])


def frame_from_points(p1: ArrayLike, p2: ArrayLike, p3: ArrayLike) -> np.ndarray:
    """The exact frame Eq. 5-1 reads, as a 4x4 pose in the points' frame: origin P1, x axis
    towards P2, z axis towards P3 made orthogonal to x, y = z x x (right-handed).

    Raises InsertionError for non-finite, coincident or collinear points."""
    p1, p2, p3 = _vec3('P1', p1), _vec3('P2', p2), _vec3('P3', p3)
    _check_triangle(p1, p2, p3)
    x = (p2 - p1) / np.linalg.norm(p2 - p1)
    z = (p3 - p1) - np.dot(p3 - p1, x) * x
    z /= np.linalg.norm(z)
    return homogeneous(np.column_stack([x, np.cross(z, x), z]), p1)


def third_point(p1: ArrayLike, p2: ArrayLike, direction: ArrayLike, *,
                length_m: float | None = None) -> np.ndarray:
    """A third frame point for a two-marker target (the card and the site carry two markers each,
    §5.2): P1 + length * (the part of `direction` orthogonal to P1-P2), so that P3 lies on the
    frame's z axis. `direction` is a known direction of the target in the same frame (the
    target's up from the inclinometer and mast encoders, or its face normal; under the planar
    assumption of §5.2 it fixes the rotation about the marker line). length_m defaults to
    |P2 - P1|."""
    p1, p2, d = _vec3('P1', p1), _vec3('P2', p2), _vec3('direction', direction)
    x = p2 - p1
    lx = np.linalg.norm(x)
    if lx == 0.0:
        raise InsertionError('P1 and P2 coincide')
    x /= lx
    z = d - np.dot(d, x) * x
    nd = np.linalg.norm(d)
    if nd == 0.0 or np.linalg.norm(z) / nd < COLLINEAR_SINE:
        raise InsertionError('direction is (nearly) parallel to P1-P2: it fixes no frame')
    length = lx if length_m is None else float(length_m)
    if not (np.isfinite(length) and length > 0):
        raise InsertionError(f'length_m must be finite and > 0, got {length_m}')
    return p1 + length * z / np.linalg.norm(z)


def homogeneous(r: ArrayLike, p: ArrayLike) -> np.ndarray:
    """4x4 [[R, p], [0, 1]] (the block form of Eq. 5-2 and 5-3)."""
    m = np.asarray(r, float)
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        raise InsertionError('rotation must be a finite 3x3 matrix')
    if not np.allclose(m.T @ m, np.eye(3), atol=1e-6) or np.linalg.det(m) < 0:
        raise InsertionError('not a proper rotation matrix')
    t = np.eye(4)
    t[:3, :3] = m
    t[:3, 3] = _vec3('translation', p)
    return t


def invert(t: ArrayLike) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    a = _transform('transform', t)
    out = np.eye(4)
    out[:3, :3] = a[:3, :3].T
    out[:3, 3] = -a[:3, :3].T @ a[:3, 3]
    return out


def a_vt(p1: ArrayLike, p2: ArrayLike, p3: ArrayLike) -> np.ndarray:
    """Eq. 5-2: A_VT, the frame of the points P1 (origin), P2 (x axis), P3 (z axis) measured in
    the vision frame R_V: [[R^x R^y R^z, P_1], [0, 1]] with the angles of the exact frame (so
    Eq. 5-2's composition reproduces the frame; see euler_eq_5_1 for the printed approximation).
    The same function gives A_VO for the goal's (insertion site's) points."""
    frame = frame_from_points(p1, p2, p3)
    return homogeneous(rotation_from_euler(euler_from_rotation(frame[:3, :3])), frame[:3, 3])


def a_ts(r_ts: ArrayLike, p_ts: ArrayLike) -> np.ndarray:
    """Eq. 5-3: A_TS = [[R_TS, P_TS], [0, 1]], the end-effector frame R_T in the arm-base frame
    R_S, from the slave arm's kinematics (forward kinematics composed with the card offset)."""
    return homogeneous(r_ts, p_ts)


@dataclass(frozen=True)
class RequiredMotion:
    """The motion that takes the object (card) frame to its goal.

    In the vision frame R_V (Eq. 5-4): translation_v = P_O1 - P_R1 (goal origin minus object
    origin), euler_difference_v = R_O - R_RT (Euler angles, Eq. 5-2 order, as Eq. 5-4 writes
    it; meaningful for small differences), rotation_v the exact rotation R_goal R_RT^T.
    In the slave's arm-base frame R_S (Eq. 5-4 transformed by A_TS A_VT^-1): translation_s,
    rotation_s (3x3) and rotvec_s (axis * angle, rad), the rotation being about the object
    frame's origin; euler_s its (R_x, R_y, R_z). goal_s is the object frame's goal pose in R_S.
    covariance_s (6x6 over translation_s, rotvec_s) when the point covariances were given."""

    translation_v: np.ndarray
    euler_difference_v: np.ndarray
    rotation_v: np.ndarray
    translation_s: np.ndarray
    rotation_s: np.ndarray
    rotvec_s: np.ndarray
    euler_s: np.ndarray
    goal_s: np.ndarray
    covariance_s: np.ndarray | None = None

    @property
    def displacement_error_m(self) -> float:
        return float(np.linalg.norm(self.translation_s))

    @property
    def angle_error_rad(self) -> float:
        return float(np.linalg.norm(self.rotvec_s))

    @property
    def twist_s(self) -> np.ndarray:
        """(translation_s, rotvec_s) as one 6-vector."""
        return np.concatenate([self.translation_s, self.rotvec_s])


def required_motion(a_vt_: ArrayLike, a_vo: ArrayLike, a_ts_: ArrayLike, *,
                    goal_offset: ArrayLike | None = None) -> RequiredMotion:
    """Eq. 5-4 and its transformation into the slave's base frame (§5.1).

    a_vt_: A_VT (object frame in R_V), a_vo: A_VO (site frame in R_V), a_ts_: A_TS (object frame
    in the slave's arm-base frame R_S). goal_offset: the object frame's goal pose in the site
    frame (a 4x4 from the task model: where the card's marker frame is when the card is where it
    should be, e.g. seated, or at the pre-insertion stand-off); identity by default, which is
    Eq. 5-4's P_O1 - P_R1 and R_O - R_RT.

    The camera's pose in R_S follows from the two: A_SV = A_TS A_VT^-1 (the camera's own pose
    is never needed), and the goal in R_S is A_TS A_VT^-1 A_VO goal_offset."""
    vt = _transform('A_VT', a_vt_)
    vo = _transform('A_VO', a_vo)
    ts = _transform('A_TS', a_ts_)
    g = np.eye(4) if goal_offset is None else _transform('goal_offset', goal_offset)
    goal_v = vo @ g
    translation_v = goal_v[:3, 3] - vt[:3, 3]
    euler_difference_v = euler_from_rotation(goal_v[:3, :3]) - euler_from_rotation(vt[:3, :3])
    rotation_v = goal_v[:3, :3] @ vt[:3, :3].T
    s_from_v = ts @ invert(vt)
    goal_s = s_from_v @ goal_v
    rotation_s = goal_s[:3, :3] @ ts[:3, :3].T
    return RequiredMotion(
        translation_v=translation_v, euler_difference_v=euler_difference_v,
        rotation_v=rotation_v, translation_s=goal_s[:3, 3] - ts[:3, 3], rotation_s=rotation_s,
        rotvec_s=Rotation.from_matrix(rotation_s).as_rotvec(),
        euler_s=euler_from_rotation(rotation_s), goal_s=goal_s)


def _points(name: str, p: ArrayLike) -> np.ndarray:
    a = np.asarray(p, float)
    if a.shape != (3, 3):
        raise InsertionError(f'{name} must be (3, 3): P1, P2, P3 as rows, got {a.shape}')
    if not np.all(np.isfinite(a)):
        raise InsertionError(f'{name} must be finite')
    return a


def required_motion_from_points(object_points: ArrayLike, site_points: ArrayLike, a_ts_: ArrayLike,
                                *, goal_offset: ArrayLike | None = None,
                                covariances: ArrayLike | None = None, step_m: float = 1e-6
                                ) -> RequiredMotion:
    """Eq. 5-2 for both frames, then Eq. 5-4 in R_S, from the measured points.

    object_points, site_points: (3, 3), rows P1, P2, P3 in R_V (P1 origin, P2 on x, P3 on z).
    covariances: optional (6, 3, 3), the 3x3 covariance of each point (object P1..P3, then site
    P1..P3, e.g. Eq. 3-7 stereo covariances); the result's covariance_s is their first-order
    propagation (central differences of step_m) to (translation_s, rotvec_s), A_TS taken as
    exact (the arm's encoders are far finer than the stereo ranges)."""
    obj = _points('object_points', object_points)
    site = _points('site_points', site_points)

    def solve(o: np.ndarray, s: np.ndarray) -> RequiredMotion:
        return required_motion(a_vt(*o), a_vt(*s), a_ts_, goal_offset=goal_offset)

    out = solve(obj, site)
    if covariances is None:
        return out
    c = np.asarray(covariances, float)
    if c.shape != (6, 3, 3) or not np.all(np.isfinite(c)):
        raise InsertionError(f'covariances must be a finite (6, 3, 3) array, got {c.shape}')
    if not np.allclose(c, np.transpose(c, (0, 2, 1)), atol=1e-12) or \
            np.any(np.linalg.eigvalsh(c) < -1e-15):
        raise InsertionError('covariances must be symmetric positive semi-definite')
    if not (np.isfinite(step_m) and step_m > 0):
        raise InsertionError('step_m must be > 0')
    x0 = np.concatenate([obj.ravel(), site.ravel()])

    def f(x: np.ndarray) -> np.ndarray:
        m = solve(x[:9].reshape(3, 3), x[9:].reshape(3, 3))
        return m.twist_s

    jac = _jacobian(f, x0, step_m)
    cov_in = np.zeros((18, 18))
    for k in range(6):
        cov_in[3 * k:3 * k + 3, 3 * k:3 * k + 3] = c[k]
    cov = jac @ cov_in @ jac.T
    return RequiredMotion(**{**out.__dict__, 'covariance_s': 0.5 * (cov + cov.T)})


def _jacobian(f: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, h: float) -> np.ndarray:
    cols = []
    for i in range(x0.size):
        d = np.zeros_like(x0)
        d[i] = h
        cols.append((f(x0 + d) - f(x0 - d)) / (2 * h))
    return np.column_stack(cols)
