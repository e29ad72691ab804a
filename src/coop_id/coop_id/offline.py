"""Identification from a recorded bag, without DDS: the identifier's sample stream (IMU,
inclinometer and F/T of the same stamp, as the node pairs them) read with rover_bag's batch
reader and fed to the same core (`identifier_core.Identifier`) in the node's windows."""
from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from coop_common.dynparams import PARAM_NAMES

from .consistency import Report
from .errors import CoopIdError
from .identifier_core import Identifier, IdentifierConfig
from .model import SensorNoise
from .pairing import QUEUE_S, SamplePairer, stamp_ns

#: the pairing's defaults, the identifier node's too (its parameters sync_tolerance_s,
#: ft_force_limit_n, ft_torque_limit_nm)
SYNC_TOLERANCE_S, FT_FORCE_LIMIT_N, FT_TORQUE_LIMIT_NM = 0.002, 200.0, 50.0


class BagError(CoopIdError):
    """The bag holds no identification stream for the rover."""


def ident_topics(rover: str) -> tuple[str, str, str]:
    """The IMU, inclinometer and F/T topics of `rover` in a bag."""
    return (f'/{rover}/imu', f'/{rover}/inclinometer', f'/{rover}/arm/wrench')


def bag_samples(bag: str | Path, *, rover: str = 'rover1',
                tolerance_s: float = SYNC_TOLERANCE_S, force_limit: float = FT_FORCE_LIMIT_N,
                torque_limit: float = FT_TORQUE_LIMIT_NM, rejects: Counter | None = None,
                ) -> tuple[np.ndarray, np.ndarray]:
    """(stamps_ns, rows) of the identifier's sample stream from the bag: its messages, in their
    recorded order, through the node's pairing (pairing.SamplePairer: the IMU sample with the
    inclinometer and F/T samples nearest its stamp within `tolerance_s`, saturated samples
    skipped; the defaults are the node's). Rows: specific force (3), gyro (3), roll, pitch,
    force (3), torque (3). `rejects`, if given, counts the samples skipped, by reason."""
    # rosbags: only the bag paths need it; the identifier node imports this module
    from rover_bag.bagio import BagError as RawBagError  # noqa: PLC0415
    from rover_bag.bagio import read_messages  # noqa: PLC0415

    topics = ident_topics(rover)
    stamps: list[int] = []
    rows: list[np.ndarray] = []
    heard: Counter[str] = Counter()
    skipped = rejects if rejects is not None else Counter()

    def on_sample(t: int, row: np.ndarray) -> None:
        stamps.append(t)
        rows.append(row)

    pairer = SamplePairer(int(QUEUE_S * IdentifierConfig.rate_hz),
                          tolerance_ns=round(tolerance_s * 1e9),
                          force_limit=force_limit, torque_limit=torque_limit,
                          on_sample=on_sample, on_reject=lambda r, _d: skipped.update([r]))
    try:
        for m in read_messages(bag, list(topics)):
            msg, t = m.msg, stamp_ns(m.msg.header)
            heard[m.topic] += 1
            if m.topic == topics[0]:
                a, w = msg.linear_acceleration, msg.angular_velocity
                pairer.imu(t, [a.x, a.y, a.z], [w.x, w.y, w.z])
            elif m.topic == topics[1]:
                pairer.inclinometer(t, msg.roll, msg.pitch, msg.saturated)
            else:
                f, n = msg.wrench.force, msg.wrench.torque
                pairer.wrench(t, [f.x, f.y, f.z], [n.x, n.y, n.z])
    except RawBagError as exc:
        raise BagError(str(exc)) from exc
    pairer.flush()
    if not rows:
        counts = {t: heard[t] for t in topics}
        raise BagError(f'{bag}: no instant with all of {list(topics)} ({counts}; skipped: '
                       f'{dict(skipped)})')
    return np.array(stamps, dtype=np.int64), np.stack(rows)


def sensor_noise(acc_var: ArrayLike, gyro_var: ArrayLike, incl_var: ArrayLike,
                 force_std: float = 0.0) -> dict[int, SensorNoise] | None:
    """The errors-in-variables noise model from the sensors' published variances (IMU
    covariance diagonals, inclinometer roll/pitch variances) and the F/T force sigma; None
    when a variance is missing (zero, negative or not finite): then no bias correction."""
    v = [np.asarray(a, dtype=float) for a in (acc_var, gyro_var, incl_var)]
    if not all(np.all(np.isfinite(a)) and np.all(a > 0) for a in v):
        return None
    return {0: SensorNoise(np.sqrt(v[0]), np.sqrt(v[1]), np.sqrt(v[2]), np.full(3, force_std))}


def bag_sensor_noise(bag: str | Path, *, rover: str = 'rover1',
                     force_std: float = 0.0) -> dict[int, SensorNoise] | None:
    """sensor_noise() from the first IMU and inclinometer messages of the bag (as the node
    takes them from the messages before a goal)."""
    from rover_bag.bagio import read_messages  # noqa: PLC0415

    imu = incl = None
    for m in read_messages(bag, list(ident_topics(rover)[:2])):
        if m.topic.endswith('/imu') and imu is None:
            imu = m.msg
        elif m.topic.endswith('/inclinometer') and incl is None:
            incl = m.msg
        if imu is not None and incl is not None:
            break
    if imu is None or incl is None:
        return None
    return sensor_noise(np.asarray(imu.linear_acceleration_covariance)[[0, 4, 8]],
                        np.asarray(imu.angular_velocity_covariance)[[0, 4, 8]],
                        [incl.roll_variance, incl.pitch_variance], force_std)


def identify_rows(rows: np.ndarray, config: IdentifierConfig | None = None, *,
                  n_samples: int | None = None,
                  noise: dict[int, SensorNoise] | None = None) -> Report:
    """The core fed `rows` in the node's windows (the first window_s * rate_hz + 1 samples,
    then window_s * rate_hz each) up to `n_samples` (default: every whole window); `noise`
    the errors-in-variables model (sensor_noise(); None: no bias correction)."""
    cfg = config or IdentifierConfig()
    ident = Identifier(cfg, sensor_noise=noise)
    per = round(cfg.window_s * cfg.rate_hz)
    if n_samples is None:
        n_samples = 1 + per * ((len(rows) - 1) // per) if len(rows) > per else 0
    if n_samples < per + 1 or n_samples > len(rows):
        raise BagError(f'need at least {per + 1} samples (one window), have {len(rows)}')
    start, first = 0, True
    while start < n_samples:
        n = per + (1 if first else 0)
        d = rows[start:start + n]
        ident.add_samples(0, specific_force=d[:, 0:3], gyro=d[:, 3:6], incl=d[:, 6:8],
                          force=d[:, 8:11], torque=d[:, 11:14])
        ident.end_window()
        start += n
        first = False
    return ident.report


def bag_truth(bag: str | Path, *, rover: str = 'rover1') -> np.ndarray | None:
    """The true parameters the simulator latched under /sim/<rover>/parameters, or None when
    the bag has none (a real rover's bag); BagError when the record lacks a parameter."""
    from rover_bag.bagio import BagError as RawBagError  # noqa: PLC0415
    from rover_bag.bagio import bag_info, read_messages  # noqa: PLC0415

    topic = f'/sim/{rover}/parameters'
    try:
        if topic not in bag_info(bag).topics:
            return None
        for m in read_messages(bag, [topic]):
            d = dict(zip(m.msg.names, m.msg.values, strict=False))
            missing = [n for n in PARAM_NAMES if n not in d]
            if missing:
                raise BagError(f'{bag}: {topic} lacks {missing}')
            return np.array([d[n] for n in PARAM_NAMES])
    except RawBagError as exc:
        raise BagError(str(exc)) from exc
    return None
