"""Simulator configuration: defaults, YAML loading that names a bad field, validation."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

import yaml

from coop_braid.mast import DEFAULT_STAGES, MastKind

from .errors import SimError
from .worldgen import CARD_WIDTH_M, TABLE_5_1_GAPS_M


class ConfigError(SimError):
    """A world/params YAML or value that the simulator cannot use; the message names the field."""

#: the simulator's ground truth: per rover on `sim/<rover>/<name>` for these names, and the
#: world on WORLD_TOPIC, app. A.4's segment on SEGMENT_TRUTH_TOPIC; for scoring and viewing
#: only: no node that closes a loop reads them
TRUTH_NAMES = ('base_pose', 'camera_pose', 'card_pose', 'contact', 'parameters')
WORLD_TOPIC = 'sim/world'
SEGMENT_TRUTH_TOPIC = 'sim/segment'


def truth_topic(rover: str, name: str) -> str:
    """The (relative) name of one of rover `rover`'s truth topics (TRUTH_NAMES)."""
    if name not in TRUTH_NAMES:
        raise ConfigError(f'no truth topic {name!r}: one of {", ".join(TRUTH_NAMES)}')
    return f'sim/{rover}/{name}'


def is_truth_topic(topic: str) -> bool:
    """Whether a topic name (relative, or resolved in any namespace) is the simulator's
    truth."""
    parts = topic.strip('/').split('/')
    return (parts[-2:] in (WORLD_TOPIC.split('/'), SEGMENT_TRUTH_TOPIC.split('/')) or
            (len(parts) >= 3 and parts[-3] == 'sim' and parts[-1] in TRUTH_NAMES))



@dataclass(frozen=True)
class NoiseConfig:
    """§2.6.1: white noise up to `fraction` of each sensor's maximum sensed value.

    The max_* values are the peak dynamic ranges each channel senses in the thesis scenario (the
    Eq. 2-21 arm excitation of the Table 2-1 rover, steady state, noise-free; re-measured by
    test_sim_world.py::test_noise_scales_match_thesis_scenario), so fraction 0.1 gives the
    thesis's noise level. Wheel and articulation scales are the app. D rover's ranges.
    """

    fraction: float = 0.10
    inclinometer_rad: float = 0.0004
    accel_m_s2: float = 0.16
    gyro_rad_s: float = 0.001
    force_n: float = 0.8
    torque_nm: float = 1.0
    encoder_rad: float = 0.7
    tach_rad_s: float = 5.0
    pot_rad: float = 0.3
    odom_drift: float = 0.02          # odometry's random walk: 1-sigma m (and rad) per sqrt(m)
                                      # of the wheels' travel


class Integrator(StrEnum):
    """How the stiff base compliance and arm PD are integrated with the engine's step."""

    #: solved with the engine's mass matrix once per engine step (rover_sim.implicit): stable at
    #: one engine step per control step
    IMPLICIT = 'implicit'
    #: applied as explicit forces at every engine sub-step: needs >= 10 sub-steps per 5 ms
    #: (world.substeps_for); with many, the reference the implicit step is measured against
    EXPLICIT = 'explicit'


class Renderer(StrEnum):
    """Which of PyBullet's renderers draws the stereo pairs."""

    #: PyBullet's software rasteriser, in the simulator's own thread (every image validated on)
    TINY = 'tiny'
    #: PyBullet's EGL plugin (OpenGL through EGL: a GPU's driver, or Mesa's llvmpipe on the
    #: CPU); where it cannot load, TINY, with the reason in World.renderer_note
    EGL = 'egl'


#: the longest BRAID mast the simulator carries (its IK's beam search is timed up to 20 stages,
#: docs/results/braid.md)
MAX_BRAID_STAGES = 20
#: image_width x image_height x supersample^2: TinyRenderer's RGBA and depth buffers of one image
MAX_RENDERED_PIXELS = 16_000_000


@dataclass(frozen=True)
class SimConfig:
    """The simulator's settings (its parameters and config YAML)."""

    rovers: int = 2
    seed: int = 1
    occlusion_density: float = 0.08
    extent_m: float = 10.0
    slot_gap_m: float = TABLE_5_1_GAPS_M[1]   # the slot's gap along the card's width (4.5 in)
    contact_friction: float = 0.4        # Coulomb friction of the card on the site and ground
    truth_yaml: str = ''                 # '' : Table 2-1 for every rover
    physics_rate_hz: float = 200.0
    integrator: Integrator = Integrator.EXPLICIT
    physics_substeps: int = 0            # 0: 1 (implicit), the stability minimum (explicit)
    sensor_rate_hz: float = 200.0
    stereo_rate_hz: float = 4.0
    image_width: int = 320
    image_height: int = 240
    hfov_deg: float = 41.2
    supersample: int = 1                 # n x n render samples averaged per pixel (odd)
    render_workers: int = 0              # 1: the right eye drawn by a second process
    renderer: Renderer = Renderer.TINY
    real_time_factor: float = 1.0        # 0: as fast as possible
    max_linear_speed_m_s: float = 0.25   # app. D: about 25 cm/s
    max_yaw_rate_rad_s: float = 1.0
    # the camera mast: the pan/tilt head, or a BRAID chain of braid_stages on the pan turntable
    # (coop_braid.mast); a new BRAID state holds the camera where it was for braid_settle_s
    # (the legs' SMA actuators switching) and then puts it where the state's FK says
    mast: MastKind = MastKind.PAN_TILT
    braid_stages: int = DEFAULT_STAGES
    braid_settle_s: float = 1.0
    noise: NoiseConfig = field(default_factory=NoiseConfig)

    def __post_init__(self) -> None:
        for name, kind in (('integrator', Integrator), ('renderer', Renderer),
                           ('mast', MastKind)):
            try:
                object.__setattr__(self, name, kind(getattr(self, name)))
            except ValueError:
                known = ', '.join(i.value for i in kind)
                raise ConfigError(f'{name}: must be one of {known}, got '
                                  f'{getattr(self, name)!r}') from None
        checks = [
            ('rovers', 1 <= self.rovers <= 8, 'must be 1..8'),
            ('occlusion_density', 0.0 <= self.occlusion_density <= 0.5, 'must be in [0, 0.5]'),
            ('extent_m', 2.0 <= self.extent_m <= 200.0, 'must be in [2, 200]'),
            ('slot_gap_m', CARD_WIDTH_M < self.slot_gap_m <= 0.25,
             f'must be in ({CARD_WIDTH_M:.5f}, 0.25]: wider than the 4.25 in card'),
            ('contact_friction', 0.0 <= self.contact_friction <= 2.0, 'must be in [0, 2]'),
            ('physics_rate_hz', 50.0 <= self.physics_rate_hz <= 2000.0, 'must be in [50, 2000]'),
            ('physics_substeps', 0 <= self.physics_substeps <= 200, 'must be in [0, 200]'),
            ('sensor_rate_hz', 0.0 < self.sensor_rate_hz <= self.physics_rate_hz,
             'must be in (0, physics_rate_hz]'),
            ('stereo_rate_hz', 0.0 <= self.stereo_rate_hz <= 30.0, 'must be in [0, 30]'),
            ('image_width', 32 <= self.image_width <= 1920, 'must be in [32, 1920]'),
            ('image_height', 24 <= self.image_height <= 1440, 'must be in [24, 1440]'),
            ('hfov_deg', 5.0 <= self.hfov_deg <= 120.0, 'must be in [5, 120]'),
            ('render_workers', self.render_workers in (0, 1), 'must be 0 or 1'),
            ('supersample', isinstance(self.supersample, int)
             and not isinstance(self.supersample, bool) and self.supersample in (1, 3, 5, 7),
             'must be the integer 1, 3, 5 or 7'),
            ('supersample', not isinstance(self.supersample, int)
             or self.image_width * self.image_height * self.supersample ** 2
             <= MAX_RENDERED_PIXELS, f'supersample^2 x image_width x image_height must be '
             f'at most {MAX_RENDERED_PIXELS:,} rendered pixels per image'),
            ('real_time_factor', 0.0 <= self.real_time_factor <= 100.0, 'must be in [0, 100]'),
            ('braid_stages', isinstance(self.braid_stages, int)
             and 1 <= self.braid_stages <= MAX_BRAID_STAGES,
             f'must be an integer in [1, {MAX_BRAID_STAGES}]'),
            ('braid_settle_s', 0.0 <= self.braid_settle_s <= 60.0, 'must be in [0, 60]'),
            ('noise.fraction', 0.0 <= self.noise.fraction <= 1.0, 'must be in [0, 1]'),
        ]
        for name, ok, why in checks:
            value = self._lookup(name)
            if isinstance(value, float) and not math.isfinite(value):
                raise ConfigError(f'{name}: must be finite, got {value}')
            if not ok:
                raise ConfigError(f'{name}: {why}, got {value!r}')
        for f in dataclasses.fields(NoiseConfig):
            v = getattr(self.noise, f.name)
            if f.name != 'fraction' and not (isinstance(v, float) and v > 0 and math.isfinite(v)):
                raise ConfigError(f'noise.{f.name}: must be a positive number, got {v!r}')

    def _lookup(self, dotted: str) -> Any:
        obj: Any = self
        for part in dotted.split('.'):
            obj = getattr(obj, part)
        return obj

    def replace(self, **changes: Any) -> SimConfig:
        return dataclasses.replace(self, **changes)


def _coerce(name: str, value: Any, default: Any) -> Any:
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f'{name}: expected true/false, got {value!r}')
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f'{name}: expected an integer, got {value!r}')
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f'{name}: expected a number, got {value!r}')
        return float(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ConfigError(f'{name}: expected a string, got {value!r}')
        return value
    raise ConfigError(f'{name}: unsupported value {value!r}')


def config_from_mapping(data: dict[str, Any], base: SimConfig | None = None) -> SimConfig:
    """Overlay a mapping (as read from YAML) on `base`; unknown or mistyped fields raise
    ConfigError naming the field."""
    base = base or SimConfig()
    if not isinstance(data, dict):
        raise ConfigError('top level: expected a mapping of field names to values')
    top = {f.name: f for f in dataclasses.fields(SimConfig)}
    changes: dict[str, Any] = {}
    for key, value in data.items():
        if key not in top:
            raise ConfigError(f'{key}: unknown field (known: {", ".join(sorted(top))})')
        if key == 'noise':
            if not isinstance(value, dict):
                raise ConfigError('noise: expected a mapping')
            nf = {f.name for f in dataclasses.fields(NoiseConfig)}
            nchanges = {}
            for nk, nv in value.items():
                if nk not in nf:
                    known = ', '.join(sorted(nf))
                    raise ConfigError(f'noise.{nk}: unknown field (known: {known})')
                nchanges[nk] = _coerce(f'noise.{nk}', nv, getattr(base.noise, nk))
            changes['noise'] = dataclasses.replace(base.noise, **nchanges)
        else:
            changes[key] = _coerce(key, value, getattr(base, key))
    return dataclasses.replace(base, **changes)


def load_config(path: str | Path, base: SimConfig | None = None) -> SimConfig:
    """Read a world/params YAML file; raises ConfigError naming the bad field."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ConfigError(f'{path}: cannot read: {exc}') from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f'{path}: not valid YAML: {exc}') from exc
    if data is None:
        return base or SimConfig()
    try:
        return config_from_mapping(data, base)
    except ConfigError as exc:
        raise ConfigError(f'{path}: {exc}') from exc
