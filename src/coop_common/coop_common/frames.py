"""The transform tree (REP 105) of a team of rovers: frame names and the transforms between them,
computed from the rover's geometry (`rover_geometry`), its odometry and its mast encoders. No
rclpy: the simulator, the hardware bridge and the stereo node turn these into `/tf` and
`/tf_static` (`coop_common.tf_tree`); the live view into Foxglove frame transforms.

    map                                        the team's common frame (the stereo nodes' estimate)
    └─ <r>/odom                                each rover's odometry frame
       └─ <r>/base_link                        the base c.g., x forward, z up (REP 103)
          ├─ <r>/ft_sensor_link                the arm's F/T sensor, at the nominal mount r_2
          └─ <r>/mast_pan_link                 pan joint (turns about z)
             └─ <r>/mast_tilt_link             tilt joint (turns about y; positive looks down)
                └─ <r>/left_camera_optical_frame     z forward, x right, y down
                   └─ <r>/right_camera_optical_frame the stereo baseline along x

Every name carries the team's `prefix` (`team_a/` gives `team_a/map`, `team_a/rover1/odom`), so
two teams in one ROS graph never share a frame. The simulator's true poses, for viewing and
scoring only, hang from the map as `<prefix>truth/<r>/base_link` and
`<prefix>truth/<r>/left_camera_optical_frame`.
"""
from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
from scipy.spatial.transform import Rotation

from .errors import CoopCommonError
from .params import ParamSpec
from .rover_geometry import (
    BASE_HEIGHT_M,
    CAMERA_OFFSET,
    MAST_JOINTS,
    MAST_POSITION,
    NOMINAL_CG_TO_ARM,
    OPTICAL_IN_TILT,
    STEREO_BASELINE_M,
    TILT_ABOVE_PAN_M,
)

__all__ = ['CAMERA_SIDES', 'FRAME_PARAMS', 'TRUTH', 'CameraSide', 'FrameError', 'RoverFrames',
           'Transform',
           'check_frame_params', 'check_prefix', 'mast_transforms',
           'odom_transform', 'quat_of', 'static_transforms', 'truth_transforms']

#: the prefix of the simulator's true frames (after the team's)
TRUTH = 'truth/'
#: one frame name segment, as ROS names allow
_SEGMENT = r'[A-Za-z_][A-Za-z0-9_]*'
_PREFIX = re.compile(rf'^({_SEGMENT}/)*$')


class FrameError(CoopCommonError):
    """A transform that cannot be built from the readings given (NaN, a missing joint)."""


def check_prefix(prefix: str) -> str | None:
    """Why `prefix` is not a frame prefix ('' or segments each ending in '/', no leading '/'),
    or None."""
    if _PREFIX.match(prefix):
        return None
    return (f'frame prefix {prefix!r}: give "" or names ending in "/" (e.g. "team_a/"), '
            'no leading "/"')


#: the parameters of a node that publishes part of the tree
FRAME_PARAMS = {
    'frame_prefix': ParamSpec('', 'Prefix of every frame id this node stamps and publishes '
                              '("team_a/": team_a/map, team_a/rover1/base_link), so two teams '
                              'in one graph never share a frame; "" or names ending in "/"',
                              read_only=True),
    'publish_tf': ParamSpec(True, "Publish this node's part of the transform tree on /tf and "
                            '/tf_static (needs tf2_msgs; off without it)', read_only=True),
    'frame_check_s': ParamSpec(0.5, 'At start, listen this long (wall s) to /tf_static and '
                               'refuse to start when another node already publishes one of '
                               'our frames (a colliding frame_prefix); 0: no check', lo=0.0,
                               hi=10.0, read_only=True),
}


def check_frame_params(values: dict) -> str | None:
    """The rule FRAME_PARAMS' values obey beyond their ranges (for declare_parameters)."""
    return check_prefix(values['frame_prefix'])


#: the cameras of a rover's stereo pair
CameraSide = Literal['left', 'right']
CAMERA_SIDES: tuple[str, ...] = get_args(CameraSide)


@dataclass(frozen=True)
class RoverFrames:
    """The frame names of one rover (`rover1`) of the team with frame prefix `prefix`."""

    rover: str
    prefix: str = ''
    #: the common frame's name after the prefix
    map_name: str = 'map'

    def __post_init__(self) -> None:
        why = check_prefix(self.prefix)
        if why or not re.fullmatch(f'({_SEGMENT})?', self.rover):
            raise FrameError(why or f'rover name {self.rover!r} is not a frame name segment')

    @classmethod
    def of_namespace(cls, namespace: str, prefix: str = '', map_name: str = 'map'
                     ) -> RoverFrames:
        """The frames of the rover a node in `namespace` serves: its last part (`/team_a/rover1`
        -> rover1), as rover_sim names its rovers; a node at the root serves an unnamed one."""
        return cls(namespace.rstrip('/').rsplit('/', 1)[-1], prefix, map_name)

    def link(self, name: str) -> str:
        """`<prefix><rover>/<name>` (`<prefix><name>` for an unnamed rover)."""
        return f'{self.prefix}{self.rover}/{name}' if self.rover else f'{self.prefix}{name}'

    @property
    def map(self) -> str:
        return f'{self.prefix}{self.map_name}'

    @property
    def odom(self) -> str:
        return self.link('odom')

    @property
    def base_link(self) -> str:
        return self.link('base_link')

    @property
    def ft_sensor(self) -> str:
        return self.link('ft_sensor_link')

    @property
    def mast_pan(self) -> str:
        return self.link('mast_pan_link')

    @property
    def mast_tilt(self) -> str:
        return self.link('mast_tilt_link')

    def optical(self, side: CameraSide) -> str:
        """`left` or `right` camera's optical frame; FrameError for another side."""
        if side not in CAMERA_SIDES:
            raise FrameError(f'camera side must be one of {list(CAMERA_SIDES)}, got {side!r}')
        return self.link(f'{side}_camera_optical_frame')

    def truth(self, name: str) -> str:
        """The simulator's true pose of frame `name` (`base_link`, ...)."""
        return RoverFrames(self.rover, self.prefix + TRUTH).link(name)

    def body(self) -> tuple[str, ...]:
        """The frames below odom: what the rover's source (the simulator, the bridge) publishes
        the transforms of."""
        return (self.base_link, self.ft_sensor, self.mast_pan, self.mast_tilt,
                self.optical('left'), self.optical('right'))

    def all(self) -> tuple[str, ...]:
        """Every frame this rover's tree holds below the map (not the truth)."""
        return (self.odom, *self.body())


@dataclass(frozen=True)
class Transform:
    """`child`'s pose in `parent`: translation (m) and unit quaternion (x, y, z, w)."""

    parent: str
    child: str
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)

    @classmethod
    def from_matrix(cls, parent: str, child: str, m: np.ndarray) -> Transform:
        m = np.asarray(m, float)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise FrameError(f'{parent} -> {child}: not a finite 4x4 transform')
        t = m[:3, 3]
        return cls(parent, child, (float(t[0]), float(t[1]), float(t[2])), quat_of(m[:3, :3]))

    def matrix(self) -> np.ndarray:
        x, y, z, w = self.rotation
        m = np.eye(4)
        m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
        m[:3, 3] = self.translation
        return m


def quat_of(r: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w), w >= 0, of a rotation matrix (scipy: stable at 180 deg
    too)."""
    q = Rotation.from_matrix(np.asarray(r, float)).as_quat()
    if q[3] < 0:
        q = -q
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


def _xyz(v: Sequence[float] | np.ndarray) -> tuple[float, float, float]:
    """A 3-vector's components as floats."""
    return float(v[0]), float(v[1]), float(v[2])


def _about_z(a: float) -> tuple[float, float, float, float]:
    return 0.0, 0.0, math.sin(a / 2), math.cos(a / 2)


def _about_y(a: float) -> tuple[float, float, float, float]:
    return 0.0, math.sin(a / 2), 0.0, math.cos(a / 2)


def _finite(what: str, *values: float) -> None:
    if not all(math.isfinite(v) for v in values):
        raise FrameError(f'{what}: not finite ({", ".join(f"{v:g}" for v in values)})')


def static_transforms(frames: RoverFrames, *,
                      cg_to_arm: Sequence[float] = NOMINAL_CG_TO_ARM) -> list[Transform]:
    """The parts of the rover's tree that never move: the F/T sensor at the arm mount r_2 (the
    design's nominal one: the identified r_2 is an estimate with its own topic, not a frame),
    the left camera in the tilt link, the right camera a baseline along its x."""
    r2 = [float(v) for v in cg_to_arm]
    if len(r2) != 3:
        raise FrameError(f'cg_to_arm needs 3 values, got {len(r2)}')
    _finite('cg_to_arm', *r2)
    return [
        Transform(frames.base_link, frames.ft_sensor, (r2[0], r2[1], r2[2])),
        Transform(frames.mast_tilt, frames.optical('left'),
                  _xyz(CAMERA_OFFSET), quat_of(OPTICAL_IN_TILT)),
        Transform(frames.optical('left'), frames.optical('right'), (STEREO_BASELINE_M, 0.0, 0.0)),
    ]


def mast_transforms(frames: RoverFrames, names: Sequence[str],
                    positions: Sequence[float]) -> list[Transform]:
    """base_link -> pan link -> tilt link from a joint state's names and positions (rad).
    FrameError when a mast joint is missing or not finite: no transform rather than a wrong
    one."""
    if len(names) != len(positions):
        raise FrameError(f'joint state with {len(names)} names and {len(positions)} positions')
    by_name = dict(zip(names, positions, strict=False))
    missing = [j for j in MAST_JOINTS if j not in by_name]
    if missing:
        raise FrameError(f'joint state without {", ".join(missing)}')
    pan, tilt = (float(by_name[j]) for j in MAST_JOINTS)
    _finite('mast joints', pan, tilt)
    return [
        Transform(frames.base_link, frames.mast_pan, _xyz(MAST_POSITION),
                  _about_z(pan)),
        Transform(frames.mast_pan, frames.mast_tilt, (0.0, 0.0, TILT_ABOVE_PAN_M),
                  _about_y(tilt)),
    ]


def odom_transform(frames: RoverFrames, x: float, y: float, yaw: float) -> Transform:
    """odom -> base_link from the odometry's planar pose: the base's c.g. BASE_HEIGHT_M above
    the odometry frame's ground (as `rover_geometry.camera_in_map` places it)."""
    _finite('odometry', x, y, yaw)
    return Transform(frames.odom, frames.base_link, (float(x), float(y), BASE_HEIGHT_M),
                     _about_z(yaw))


def truth_transforms(frames: RoverFrames, base: np.ndarray,
                     camera: np.ndarray) -> list[Transform]:
    """map -> truth/<r>/base_link and map -> truth/<r>/left_camera_optical_frame from the
    simulator's true 4x4 poses: beside the estimated tree, never in it."""
    return [Transform.from_matrix(frames.map, frames.truth('base_link'), base),
            Transform.from_matrix(frames.map, frames.truth('left_camera_optical_frame'),
                                  camera)]
