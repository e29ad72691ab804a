"""URDF of one thesis rover (Fig. 2-2, app. D): a rigid base whose link frame sits at its c.g.,
a 6-axis F/T sensor at r_2, a 4-DOF 1 kg arm on it, and a pan/tilt stereo mast.

The base carries no collision shape: it floats on its 6-DOF compliance (Eq. B-3), applied by
`world.World`, and nothing else touches it. The card in rover 2's gripper is the one link with a
collision shape: it is what touches the insertion site (ch. 5).
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from coop_common.dynparams import BaseParameters
from coop_common.rover_geometry import (  # noqa: F401
    ARM_JOINT1_ABOVE_SENSOR_M,
    ARM_JOINTS,
    ARM_LIMITS_RAD,
    ARM_LINKS,
    ARM_MASS,
    CAMERA_OFFSET,
    CARD_OFFSET_M,
    MAST_JOINTS,
    MAST_POSITION,
    MAST_TILT_LIMITS_RAD,
    OPTICAL_IN_TILT,
    STEREO_BASELINE_M,
    TILT_ABOVE_PAN_M,
    ArmLink,
    CameraMount,
    ReachError,
    camera_mount,
    card_fk,
    card_ik,
)

# (the kinematic geometry above is coop_common's, shared with the nodes; re-exported here)
from .worldgen import Card

WHEELS = ('wheel_fl', 'wheel_fr', 'wheel_rl', 'wheel_rr')
ARM_EFFORT_NM = (12.0, 12.0, 8.0, 4.0)
ARM_VELOCITY_RAD_S = (3.0, 3.0, 3.0, 3.0)
SENSOR_MASS = 1e-3
CARD_IN_LINK_4 = f'{CARD_OFFSET_M} 0 0'
#: mast links: (mass, c.o.m. in the base frame at pan = tilt = 0, principal inertia)
#: Light (50 g in all) so that the Table 2-1 inertia less the mast's is still a physical body.
#: the stereo camera's housing (m), drawn behind the pair
CAMERA_BOX_M = (0.04, 0.08, 0.04)
MAST_PAN = (0.02, (MAST_POSITION[0], MAST_POSITION[1], MAST_POSITION[2] + 0.02), (1e-5,) * 3)
MAST_TILT = (0.03, (MAST_POSITION[0] + 0.02, MAST_POSITION[1], MAST_POSITION[2] + 0.10),
             (2e-5,) * 3)


def _shift(mass: float, c: np.ndarray) -> np.ndarray:
    """Parallel-axis term m (|c|^2 E - c c^T)."""
    c = np.asarray(c, dtype=float)
    return mass * (float(c @ c) * np.eye(3) - np.outer(c, c))


def base_link_inertial(params: BaseParameters, *, damper_lag_s: float = 0.0
                       ) -> tuple[float, np.ndarray, np.ndarray]:
    """(mass, c.o.m. offset, inertia about that c.o.m.) of the base link alone such that the
    sprung body the compliance holds, base link + mast at home, has exactly the true mass, c.g.
    (the link origin) and inertia tensor of `params`: the mast rides on the base, and Eq. 2-1's
    m_1, I_1 are those of everything sprung except the arm beyond the F/T sensor.

    damper_lag_s: how much older than the pose the angular velocity is that the rotational
    damper of Eq. B-3 sees (half a physics sub-step, see compliance.FastCompliance). A damper
    torque -B w(t - d) = -B w(t) + B d w_dot(t) + O(d^2) is, at the identification's
    frequencies, an inertia -B d about the damper's axes: the engine's inertia carries +B d so
    that the simulated body's effective inertia is the true one (B_roll h/2 = 0.075 kg m^2,
    half of I_x, at the 10 sub-steps of Table 2-1). This is the implicit (midpoint) treatment
    of the damper; an explicit extrapolation would be unstable at b h / I ~ 1."""
    mast = (MAST_PAN, MAST_TILT)
    m_b = params.mass - sum(m for m, _, _ in mast)
    if m_b <= 0:
        raise ValueError(f'base mass {params.mass} kg does not exceed the mast mass')
    if damper_lag_s < 0:
        raise ValueError(f'damper_lag_s must be >= 0, got {damper_lag_s}')
    c_b = np.asarray(-sum(m * np.asarray(c) for m, c, _ in mast) / m_b)
    inertia = (params.inertia + damper_lag_s * np.diag(params.damping[3:])
               - _shift(m_b, c_b))
    for m, c, i in mast:
        inertia = inertia - np.diag(i) - _shift(m, np.asarray(c))
    eig = np.linalg.eigvalsh(inertia)
    if np.any(eig <= 0) or eig[0] + eig[1] < eig[2]:
        raise ValueError("the true inertia less the mast's is not a physical body "
                         f'(principal moments {np.round(eig, 5).tolist()})')
    return m_b, c_b, inertia


def _inertial(mass: float, com: Sequence[float], inertia: Sequence[float]) -> str:
    ix, iy, iz = inertia
    return (f'<inertial><origin xyz="{com[0]} {com[1]} {com[2]}"/><mass value="{mass}"/>'
            f'<inertia ixx="{ix}" iyy="{iy}" izz="{iz}" ixy="0" ixz="0" iyz="0"/></inertial>')


def _box(size: Sequence[float], xyz: Sequence[float] = (0, 0, 0),
         rgba: Sequence[float] = (0.6, 0.6, 0.6, 1.0)) -> str:
    return (f'<visual><origin xyz="{xyz[0]} {xyz[1]} {xyz[2]}"/><geometry><box size="{size[0]} '
            f'{size[1]} {size[2]}"/></geometry><material name="m"><color rgba="{rgba[0]} '
            f'{rgba[1]} {rgba[2]} {rgba[3]}"/></material></visual>')


def rover_urdf(name: str, params: BaseParameters, *, with_card: bool = False,
               shade: float = 0.55, damper_lag_s: float = 0.0, head: bool = True) -> str:
    """URDF text of a rover whose base has the given true parameters (damper_lag_s: see
    base_link_inertial). head False: the pan/tilt mast's post and camera head are not drawn
    (a BRAID mast carries the camera, `World` draws it; the mast links keep their masses)."""
    m_b, c_b, i = base_link_inertial(params, damper_lag_s=damper_lag_s)
    r2 = params.cg_to_arm
    c = (shade, shade * 0.95, shade * 0.85, 1.0)
    parts = [f'<robot name="{name}">',
             f'<link name="base_link"><inertial><origin xyz="{c_b[0]} {c_b[1]} {c_b[2]}"/>'
             f'<mass value="{m_b}"/><inertia ixx="{i[0, 0]}" iyy="{i[1, 1]}" '
             f'izz="{i[2, 2]}" ixy="{i[0, 1]}" ixz="{i[0, 2]}" iyz="{i[1, 2]}"/></inertial>',
             _box((0.5, 0.36, 0.14), rgba=c),
             _box((0.04, 0.04, 0.4), (-0.12, -0.10, 0.2), c) if head else '',
             '</link>',
             f'<link name="ft_sensor_link">{_inertial(SENSOR_MASS, (0, 0, 0), (1e-7,) * 3)}'
             f'{_box((0.06, 0.06, 0.03), rgba=(0.2, 0.2, 0.2, 1))}</link>',
             '<joint name="ft_sensor_joint" type="fixed"><parent link="base_link"/>'
             f'<child link="ft_sensor_link"/><origin xyz="{r2[0]} {r2[1]} {r2[2]}"/></joint>']
    parent = 'ft_sensor_link'
    offset = (0.0, 0.0, ARM_JOINT1_ABOVE_SENSOR_M)
    axes = ('0 0 1', '0 1 0', '0 1 0', '0 1 0')
    for k, link in enumerate(ARM_LINKS):
        lo, hi = ARM_LIMITS_RAD[k]
        vis = (_box((0.04, 0.04, 0.06), (0, 0, 0.03), c) if k == 0 else
               _box((link.length, 0.035, 0.035), (link.length / 2, 0, 0), c))
        parts.append(f'<link name="{link.name}">{_inertial(link.mass, link.com, link.inertia)}'
                     f'{vis}</link>')
        parts.append(f'<joint name="{ARM_JOINTS[k]}" type="revolute"><parent link="{parent}"/>'
                     f'<child link="{link.name}"/><origin xyz="{offset[0]} {offset[1]} '
                     f'{offset[2]}"/><axis xyz="{axes[k]}"/><limit lower="{lo}" upper="{hi}" '
                     f'effort="{ARM_EFFORT_NM[k]}" velocity="{ARM_VELOCITY_RAD_S[k]}"/></joint>')
        parent = link.name
        offset = (0.0, 0.0, link.length) if k == 0 else (link.length, 0.0, 0.0)
    if with_card:
        card = Card()
        size = (card.width_m, card.thickness_m, card.height_m)
        markers = ''.join(
            f'<visual><origin xyz="{u} {card.thickness_m / 2 + 0.0001} {v}" rpy="1.5708 0 0"/>'
            f'<geometry><cylinder radius="{card.marker_radius_m}" length="0.0004"/></geometry>'
            '<material name="w"><color rgba="1 1 1 1"/></material></visual>'
            for u, v in card.marker_offsets)
        parts.append(f'<link name="card_link">{_inertial(0.01, (0, 0, 0), (1e-6,) * 3)}'
                     f'{_box(size, rgba=(0.15, 0.15, 0.15, 1))}{markers}'
                     f'<collision><geometry><box size="{size[0]} {size[1]} {size[2]}"/>'
                     '</geometry></collision></link>')
        parts.append('<joint name="card_joint" type="fixed"><parent link="arm_link_4"/>'
                     f'<child link="card_link"/><origin xyz="{CARD_IN_LINK_4}"/></joint>')
    mx, my, mz = MAST_POSITION
    pan_inertial = _inertial(MAST_PAN[0], (0, 0, 0.02), MAST_PAN[2])
    parts.append(f'<link name="mast_pan_link">{pan_inertial}'
                 f'{_box((0.03, 0.03, 0.04), (0, 0, 0.02), c)}</link>')
    parts.append('<joint name="mast_pan" type="revolute"><parent link="base_link"/>'
                 f'<child link="mast_pan_link"/><origin xyz="{mx} {my} {mz}"/><axis xyz="0 0 1"/>'
                 '<limit lower="-3.1" upper="3.1" effort="5" velocity="2"/></joint>')
    cx, _cy, cz = CAMERA_OFFSET
    tilt_inertial = _inertial(MAST_TILT[0], (0.02, 0, 0.06), MAST_TILT[2])
    parts.append(f'<link name="mast_tilt_link">{tilt_inertial}'
                 + (_box(CAMERA_BOX_M, (cx - 0.02, -STEREO_BASELINE_M / 2, cz),
                         (0.1, 0.1, 0.1, 1)) if head else '') +
                 '</link>')
    parts.append('<joint name="mast_tilt" type="revolute"><parent link="mast_pan_link"/>'
                 f'<child link="mast_tilt_link"/><origin xyz="0 0 {TILT_ABOVE_PAN_M}"/>'
                 '<axis xyz="0 1 0"/>'
                 f'<limit lower="{MAST_TILT_LIMITS_RAD[0]}" upper="{MAST_TILT_LIMITS_RAD[1]}" '
                 'effort="5" velocity="2"/></joint>')
    parts.append('</robot>')
    return '\n'.join(parts)


#: Left optical frame in the tilt link: z forward (link x), x right (link -y), y down (link -z).


def arm_joint_inertias(q: np.ndarray) -> np.ndarray:
    """Inertia (kg m^2) each arm joint drives at configuration q (planar-chain estimate): joint 1
    about the vertical through the arm base, joints 2..4 about their pitch axes. Used to schedule
    the joint PD gains (joint 1's inertia falls ~200x when the arm points up)."""
    _, q2, q3, q4 = (float(v) for v in q)
    l1, l2, l3, l4 = ARM_LINKS

    def u(theta: float) -> np.ndarray:
        return np.array([np.cos(theta), -np.sin(theta)])

    t2, t3, t4 = q2, q2 + q3, q2 + q3 + q4
    c2 = l2.com[0] * u(t2)
    j3 = l2.length * u(t2)
    c3 = j3 + l3.com[0] * u(t3)
    j4 = j3 + l3.length * u(t3)
    c4 = j4 + l4.com[0] * u(t4)
    links = ((l2, c2), (l3, c3), (l4, c4))
    axial = l1.inertia[2] + sum(link.inertia[0] for link, _ in links)
    i1 = axial + sum(link.mass * c[0] ** 2 for link, c in links)
    i2 = sum(link.mass * float(c @ c) + link.inertia[1] for link, c in links)
    i3 = sum(link.mass * float((c - j3) @ (c - j3)) + link.inertia[1]
             for link, c in links[1:])
    i4 = l4.mass * l4.com[0] ** 2 + l4.inertia[1]
    return np.array([i1, i2, i3, i4])
