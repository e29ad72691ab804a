"""The 22 base dynamic parameters of thesis ch. 2 (Table 2-1 order) and their truth files."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from .errors import CoopCommonError

#: Table 2-1 row order: mass, inertia (x, y, z, xz, yz, xy), c.g. (r_2), damping (x, y, z, pitch,
#: roll, yaw), stiffness (same axes).
PARAM_NAMES: tuple[str, ...] = (
    'mass', 'Ixx', 'Iyy', 'Izz', 'Ixz', 'Iyz', 'Ixy',
    'cg_x', 'cg_y', 'cg_z',
    'b_x', 'b_y', 'b_z', 'b_pitch', 'b_roll', 'b_yaw',
    'k_x', 'k_y', 'k_z', 'k_pitch', 'k_roll', 'k_yaw',
)
PARAM_UNITS: dict[str, str] = {
    'mass': 'kg', **{n: 'kg m^2' for n in ('Ixx', 'Iyy', 'Izz', 'Ixz', 'Iyz', 'Ixy')},
    **{n: 'm' for n in ('cg_x', 'cg_y', 'cg_z')},
    **{n: 'N s/m' for n in ('b_x', 'b_y', 'b_z')},
    **{n: 'N m s/rad' for n in ('b_pitch', 'b_roll', 'b_yaw')},
    **{n: 'N/m' for n in ('k_x', 'k_y', 'k_z')},
    **{n: 'N m/rad' for n in ('k_pitch', 'k_roll', 'k_yaw')},
}
#: Table 2-1 labels, for printing the table in the thesis's layout.
PARAM_LABELS: dict[str, str] = {
    'mass': 'Mass (kg)', 'Ixx': 'Inertia I_x', 'Iyy': 'Inertia I_y', 'Izz': 'Inertia I_z',
    'Ixz': 'Inertia I_xz', 'Iyz': 'Inertia I_yz', 'Ixy': 'Inertia I_xy',
    'cg_x': 'c.g. x (m)', 'cg_y': 'c.g. y (m)', 'cg_z': 'c.g. z (m)',
    'b_x': 'Damping x', 'b_y': 'Damping y', 'b_z': 'Damping z',
    'b_pitch': 'Damping th_p', 'b_roll': 'Damping th_r', 'b_yaw': 'Damping th_v',
    'k_x': 'Stiffness x', 'k_y': 'Stiffness y', 'k_z': 'Stiffness z',
    'k_pitch': 'Stiffness th_p', 'k_roll': 'Stiffness th_r', 'k_yaw': 'Stiffness th_v',
}

DEFAULT_TRUTH_PATH = Path(__file__).resolve().parent / 'data' / 'table_2_1_truth.yaml'


class TruthFileError(CoopCommonError):
    """A truth YAML is missing a field, has an unknown one, or a physically impossible value."""


@dataclass(frozen=True)
class BaseParameters:
    """One rover's base dynamic parameters (Eq. 2-1 unknowns), SI units."""

    mass: float
    inertia: np.ndarray      # 3x3 symmetric, about the base c.g., base frame
    cg_to_arm: np.ndarray    # r_2: arm-base (F/T) position relative to the base c.g. (m)
    damping: np.ndarray      # (b_x, b_y, b_z, b_roll, b_pitch, b_yaw): REP 103 axis order x, y, z
    stiffness: np.ndarray    # (k_x, k_y, k_z, k_roll, k_pitch, k_yaw)

    @classmethod
    def from_vector(cls, x: np.ndarray) -> BaseParameters:
        d = dict(zip(PARAM_NAMES, np.asarray(x, dtype=float), strict=False))
        inertia = np.array([
            [d['Ixx'], d['Ixy'], d['Ixz']],
            [d['Ixy'], d['Iyy'], d['Iyz']],
            [d['Ixz'], d['Iyz'], d['Izz']],
        ])
        return cls(
            mass=d['mass'], inertia=inertia,
            cg_to_arm=np.array([d['cg_x'], d['cg_y'], d['cg_z']]),
            damping=np.array([d[f'b_{a}'] for a in ('x', 'y', 'z', 'roll', 'pitch', 'yaw')]),
            stiffness=np.array([d[f'k_{a}'] for a in ('x', 'y', 'z', 'roll', 'pitch', 'yaw')]),
        )

    def to_vector(self) -> np.ndarray:
        i = self.inertia
        b, k = self.damping, self.stiffness
        return np.array([
            self.mass, i[0, 0], i[1, 1], i[2, 2], i[0, 2], i[1, 2], i[0, 1],
            *self.cg_to_arm,
            b[0], b[1], b[2], b[4], b[3], b[5],
            k[0], k[1], k[2], k[4], k[3], k[5],
        ])

    def to_dict(self) -> dict[str, float]:
        return {n: float(v) for n, v in zip(PARAM_NAMES, self.to_vector(), strict=False)}


def check_physical(x: np.ndarray) -> list[str]:
    """Reasons a parameter vector is not physically consistent (empty list: consistent).

    m > 0; inertia positive definite with the triangle inequality on its principal moments;
    stiffness and damping >= 0.
    """
    p = BaseParameters.from_vector(x)
    reasons = []
    if not p.mass > 0:
        reasons.append(f'mass {p.mass:g} <= 0')
    eig = np.linalg.eigvalsh(p.inertia)
    if not np.all(eig > 0):
        reasons.append(f'inertia not positive definite (eigenvalues {np.round(eig, 6).tolist()})')
    elif not (eig[0] + eig[1] >= eig[2] - 1e-12):
        reasons.append('principal moments violate the triangle inequality')
    if np.any(p.damping < 0):
        reasons.append('negative damping')
    if np.any(p.stiffness < 0):
        reasons.append('negative stiffness')
    return reasons


def load_truth(path: str | Path | None = None) -> BaseParameters:
    """Read a truth YAML (default: Table 2-1). Raises TruthFileError naming the bad field."""
    path = Path(path) if path is not None else DEFAULT_TRUTH_PATH
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise TruthFileError(f'{path}: cannot read truth file: {exc}') from exc
    if not isinstance(data, dict):
        raise TruthFileError(f'{path}: expected a mapping of parameter name to value')
    unknown = sorted(set(data) - set(PARAM_NAMES))
    if unknown:
        raise TruthFileError(f'{path}: unknown field(s) {unknown}')
    missing = [n for n in PARAM_NAMES if n not in data]
    if missing:
        raise TruthFileError(f'{path}: missing field(s) {missing}')
    values = []
    for name in PARAM_NAMES:
        v = data[name]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise TruthFileError(f'{path}: field {name!r} must be a finite number, got {v!r}')
        values.append(float(v))
    x = np.array(values)
    reasons = check_physical(x)
    if reasons:
        raise TruthFileError(f'{path}: not physically consistent: {"; ".join(reasons)}')
    return BaseParameters.from_vector(x)
