"""Sensor models of the thesis rovers (§2.6.1 noise, app. D hardware): pure numpy.

Noise follows §2.6.1: white noise of up to `noise_fraction` of the maximum sensed value, i.e.
uniform in [-f * max, +f * max] per sample, with `max` the largest magnitude the channel is
expected to sense (configured per sensor group).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

DEG = np.pi / 180.0


@dataclass(frozen=True)
class WhiteNoise:
    """Uniform white noise bounded by fraction * max_sensed (§2.6.1)."""

    fraction: float
    max_sensed: float

    def __post_init__(self) -> None:
        if not (0.0 <= self.fraction <= 1.0):
            raise ValueError(f'noise fraction must be in [0, 1], got {self.fraction}')
        if not (self.max_sensed > 0.0):
            raise ValueError(f'max_sensed must be > 0, got {self.max_sensed}')

    @property
    def bound(self) -> float:
        return self.fraction * self.max_sensed

    @property
    def variance(self) -> float:
        """Variance of the uniform distribution on [-bound, bound]."""
        return self.bound ** 2 / 3.0

    def sample(self, rng: np.random.Generator, shape: tuple[int, ...] | int) -> np.ndarray:
        if self.bound == 0.0:
            return np.zeros(shape)
        return rng.uniform(-self.bound, self.bound, size=shape)


@dataclass(frozen=True)
class InclinometerModel:
    """Two-axis inclinometer (Crossbow CXTA02, app. D): linear range +-20 deg, Eq. D-1 calibration,
    read through an n-bit converter over the linear range.

    Volts out = V0 + S * angle_deg (Eq. D-1 solved for V_out), quantised to 2^bits levels over the
    voltage span of the linear range; outside it the output saturates.
    """

    zero_volts: tuple[float, float] = (2.406, 2.381)        # roll, pitch: Table D-1 robot 1
    sensitivity_v_per_deg: tuple[float, float] = (0.033631, 0.034733)
    linear_range_deg: float = 20.0
    bits: int = 10
    noise: WhiteNoise = WhiteNoise(0.1, 0.5 * DEG)

    def read(self, roll: float, pitch: float, rng: np.random.Generator
             ) -> tuple[np.ndarray, np.ndarray, bool]:
        """(angles_rad (roll, pitch), raw volts, saturated) for true base roll and pitch."""
        noise = self.noise.sample(rng, 2)
        angles, volts, saturated = [], [], False
        lim = self.linear_range_deg
        for k, truth in enumerate((roll, pitch)):       # scalar math: called at 200 Hz
            deg = (truth + float(noise[k])) / DEG
            if abs(deg) > lim:
                saturated = True
                deg = max(-lim, min(lim, deg))
            v0, sens = self.zero_volts[k], self.sensitivity_v_per_deg[k]
            lsb = 2.0 * lim * sens / (2 ** self.bits)
            v = v0 + round(sens * deg / lsb) * lsb
            volts.append(v)
            angles.append((v - v0) / sens * DEG)         # Eq. D-1
        return np.array(angles), np.array(volts), saturated

    def variance(self) -> float:
        """Per-axis variance (rad^2): white noise plus quantisation (lsb^2 / 12)."""
        lsb_rad = 2.0 * self.linear_range_deg / (2 ** self.bits) * DEG
        return self.noise.variance + lsb_rad ** 2 / 12.0


def wheel_speeds(v: float, w: float, *, track_m: float, radius_m: float) -> np.ndarray:
    """Skid-steer wheel speeds (fl, fr, rl, rr) in rad/s for body speed v and yaw rate w."""
    left = (v - 0.5 * track_m * w) / radius_m
    right = (v + 0.5 * track_m * w) / radius_m
    return np.array([left, right, left, right])


def odometry_step(xy: np.ndarray, yaw: np.ndarray | float, v: float, w: float, dt: float, *,
                  drift: float, track_m: float, noise: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray | float]:
    """Dead reckoning over one step of the commanded (v, w), drifting as a random walk in the
    wheels' travel d = (|v| + |w| track / 2) dt: a 1-sigma error of drift sqrt(d x 1 m) per
    position axis and drift sqrt(d / 1 m) rad of heading (2 cm and 0.02 rad after a metre with
    drift 0.02, 4 cm after four). noise: standard normals (..., 3) for (x, y, heading); xy
    (..., 2) and yaw (...) broadcast with it, for one rover or many."""
    e = math.sqrt((abs(v) + abs(w) * track_m / 2) * dt) * drift * np.asarray(noise, float)
    yaw = yaw + w * dt + e[..., 2]
    heading = np.stack([np.cos(yaw), np.sin(yaw)], axis=-1)
    return xy + dt * v * heading + e[..., :2], yaw


def specific_force(accel_world: np.ndarray, r_base: np.ndarray) -> np.ndarray:
    """Accelerometer reading in the base frame: a - g (REP 145, +9.81 z at rest)."""
    return r_base.T @ (np.asarray(accel_world) - np.array([0.0, 0.0, -9.81]))
