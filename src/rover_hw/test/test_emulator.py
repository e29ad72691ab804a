"""The emulated controller: its frames decode, it follows commands, stops on its own watchdog and
on an e-stop, and talks over a real pseudo-terminal."""
from __future__ import annotations

import os
import threading

import pytest
import serial

from rover_hw import protocol as p
from rover_hw.emulator import Device, Faults, PtyEmulator, make_world


@pytest.fixture(scope='module')
def world():
    w = make_world(seed=2)
    yield w
    w.close()


def run(dev: Device, n: int, host: bytes = b'') -> list[p.Frame]:
    dec = p.Decoder()
    out = []
    for _ in range(n):
        acks = dev.receive(host) if host else b''
        out += dec.feed(acks + dev.tick())
    assert dec.bad_total == 0
    return out


def drive(v: float) -> bytes:
    w = v / 0.06
    return p.encode(p.DriveCommand(p.DriveMode.VELOCITY, (w, w, w, w)), 0)


def test_sensor_frames_and_heartbeats(world):
    dev = Device(world)
    frames = run(dev, 40)
    kinds = [f.type for f in frames]
    assert kinds.count(p.FrameType.SENSORS) == 40 and kinds.count(p.FrameType.HEARTBEAT) == 2
    s = frames[-1].payload if frames[-1].type is p.FrameType.SENSORS else frames[-2].payload
    assert abs(s.accel[2] * p.ACCEL_M_S2 - 9.81) < 0.5          # specific force at rest
    volts = s.incl[0] * p.INCL_VOLTS
    assert abs(p.incl_angle(volts, 2.406, 0.033631)) < 0.01


def test_follows_drive_then_stops_when_the_host_falls_silent(world):
    dev = Device(world, host_timeout_s=0.1)
    frames = run(dev, 20, host=drive(0.2))
    tach = [f for f in frames if f.type is p.FrameType.SENSORS][-1].payload.tachometers
    assert tach[0] * p.TACH_RAD_S > 2.0
    assert dev.motors_enabled
    frames = run(dev, 30)          # 150 ms of silence
    assert not dev.motors_enabled
    last = [f for f in frames if f.type is p.FrameType.SENSORS][-1].payload
    assert abs(last.tachometers[0] * p.TACH_RAD_S) < 1.0      # tach noise bound 0.5 rad/s


def test_estop_acked_within_one_cycle_and_commands_refused(world):
    dev = Device(world)
    run(dev, 5, host=drive(0.2))
    acks = dev.receive(p.encode(p.EStop(True), 77))
    frames = list(p.Decoder().feed(acks))
    assert frames[0].payload == p.Ack(int(p.FrameType.ESTOP), 77, p.AckStatus.OK)
    assert world.odometry(0)[2] == 0.0            # commanded speed zeroed at once
    refused = list(p.Decoder().feed(dev.receive(drive(0.2))))
    assert refused[0].payload.status is p.AckStatus.REFUSED
    assert dev.receive(drive(0.0)) == b''          # a stop is never refused
    dev.receive(p.encode(p.EStop(False), 78))
    assert not dev.estop


def test_pty_round_trip_and_unplug(tmp_path, world):
    link = tmp_path / 'rover1_hw'
    emu = PtyEmulator(Device(world, faults=Faults(unplug_at_s=0.1, unplug_s=0.1)), link=link,
                      rate=1.0, log=lambda m: None)
    emu.open()
    port = serial.serial_for_url(str(link), timeout=0.05)
    t = threading.Thread(target=emu.run, args=(0.15,))
    t.start()
    dec = p.Decoder()
    got = []
    try:
        while t.is_alive() and len(got) < 10:
            got += dec.feed(port.read(256))
    finally:
        t.join()
        port.close()
        emu.close()
    assert len(got) >= 10 and dec.bad_total == 0
    assert os.path.islink(link) and os.readlink(link) == emu.slave_path


def _references(arrivals: list[int], lead: int) -> list[float]:
    """Arm joint 1's reference at each control instant while a host streams timed set-points of
    0.3 sin(2 pi t), one per control period and `lead` periods ahead, `arrivals[k]` of them
    landing before instant k."""
    import math
    w = make_world(seed=3)
    try:
        dev = Device(w)
        t0, dt, sent, refs = w.time_s, w.dt, 0, []
        for n in arrivals:
            for _ in range(n):
                t = t0 + (sent + lead) * dt
                q = 0.3 * math.sin(2 * math.pi * t)
                qd = 0.6 * math.pi * math.cos(2 * math.pi * t)
                dev.receive(p.encode(p.ArmCommand((q, 0.0, 0.0, 0.0), (qd, 0.0, 0.0, 0.0),
                                                  round(t * 1e6)), sent))
                sent += 1
            dev.tick(send=False)
            refs.append(float(w.rovers[0].arm.target(w.time_s)[0][0]))
        assert dev.late_setpoints == 0
        return refs
    finally:
        w.close()


@pytest.mark.parametrize('lead', [4, 30])
def test_timed_setpoints_give_one_path_however_they_arrive(lead):
    """A set-point's arrival time within its lead leaves the joint reference unchanged: the
    bridge's timer and the link jitter by milliseconds, and a reference that jittered with
    them would shake the base it is there to identify."""
    steady = [1] * 60
    bunched = [1] * 10 + [0, 2, 1, 0, 0, 3, 2, 1, 0, 1] * 5
    assert sum(bunched) == sum(steady)
    a, b = _references(steady, lead), _references(bunched, lead)
    assert max(abs(x - y) for x, y in zip(a[lead + 16:], b[lead + 16:], strict=False)) < 1e-9
    assert max(abs(x) for x in a) > 0.1                      # the arm was told to move
