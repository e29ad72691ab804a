"""Computers on a field network, on one Linux machine: each host a network namespace joined to a
switch (a bridge in a namespace of its own) by a veth link that can be rate-limited and cut
(no rclpy; needs root, `ip` and `tc`).

    with FieldNetwork(['base', 'rover1', 'rover2'], rate_mbit=2.0) as net:
        p = net.start('rover1', ['ros2', 'run', ...], env=net.ros_env(domain_id=7))
        net.cut('rover1'); ...; net.restore('rover1')
        net.link_bytes()                      # bytes each host sent and received on its link

Every host sees only its loopback and its `eth0` (10.77.0.<i>/24, multicast routed there), so
processes in two hosts talk over the link or not at all: DDS discovery runs as on a field network
(SPDP multicast on the switch; the bridge floods it, snooping off). A link's rate limit is a
`tc tbf` on both of its ends (upload and download); a cut is the switch's end of the link set
down (both directions), a restore sets it up. Nothing outside the namespaces this object made
carries its traffic.

Names carry the creating process's id (`coop<pid>-<host>`, `coop<pid>x<k>-<host>` for its
k-th network), so parallel runs never meet, and a run that was killed before it could clean up
is cleaned up by the next one (`remove_stale`). Leaving the `with` block (also by an exception,
or a SIGTERM while no other handler is set) stops every process started in the hosts and
deletes the namespaces, which deletes their links and the switch.
"""
from __future__ import annotations

import contextlib
import itertools
import json
import os
import re
import signal
import subprocess
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import IO

from .errors import CoopCommonError

__all__ = ['FieldNetwork', 'NetnsError', 'remove_stale']

PREFIX = 'coop'
_NAME = re.compile(rf'^{PREFIX}(\d+)(?:x\d+)?-')
_made_here = itertools.count()
SUBNET = '10.77.0'
#: a Fast DDS profile with the UDPv4 transport only: no shared memory between hosts that share
#: one kernel (in the field there is none to share)
UDP_PROFILE = Path(__file__).resolve().parent / 'data' / 'fastdds_udp_only.xml'


class NetnsError(CoopCommonError):
    """A namespace, link or shaping command failed (not root, no `ip`, a bad host name)."""


def _ip(*args: str, ns: str | None = None, check: bool = True) -> subprocess.CompletedProcess:
    """Run a command (`ip ...`, `tc ...`), inside namespace `ns` if given."""
    cmd = (['ip', 'netns', 'exec', ns] if ns else []) + list(args)
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=30, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise NetnsError(f'{" ".join(cmd)}: {exc}') from exc
    if check and r.returncode != 0:
        raise NetnsError(f'{" ".join(cmd)}: {r.stderr.strip() or r.returncode}')
    return r


def _namespaces() -> list[str]:
    r = _ip('ip', 'netns', 'list', check=False)
    return [line.split()[0] for line in r.stdout.splitlines() if line.strip()]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _kill_in(ns: str) -> None:
    """Every process inside namespace `ns`: SIGTERM, then SIGKILL what is left after 5 s."""
    for sig, wait_s in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 2.0)):
        pids = [int(p) for p in _ip('ip', 'netns', 'pids', ns, check=False).stdout.split()]
        if not pids:
            return
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, sig)
        t_end = time.monotonic() + wait_s
        while time.monotonic() < t_end and any(_alive(p) for p in pids):
            time.sleep(0.05)


def _delete(ns: str) -> None:
    _kill_in(ns)
    _ip('ip', 'netns', 'delete', ns, check=False)


def _terminate(signum: int, frame: object) -> None:
    raise SystemExit(128 + signum)


def remove_stale() -> list[str]:
    """Delete the namespaces of runs whose process is gone (a run killed before it could clean
    up); returns their names."""
    gone = []
    for ns in _namespaces():
        m = _NAME.match(ns)
        if m and not _alive(int(m.group(1))):
            _delete(ns)
            gone.append(ns)
    return gone


class FieldNetwork:
    """Hosts on a switch (the module docstring). `rate_mbit`: every link's rate limit (None:
    the veth's own speed), `rates_mbit` another one for some hosts (a base station's radio that
    serves every rover); `burst_kbit`: the token bucket's depth."""

    def __init__(self, hosts: Sequence[str], *, rate_mbit: float | None = None,
                 rates_mbit: Mapping[str, float] | None = None,
                 burst_kbit: float = 256.0) -> None:
        if len(set(hosts)) != len(hosts) or not hosts:
            raise NetnsError(f'hosts {list(hosts)}: need distinct names')
        for h in hosts:
            if not re.fullmatch(r'[a-z][a-z0-9_]{0,20}', h):
                raise NetnsError(f'host name {h!r}: lower case letters, digits, _')
        if len(hosts) > 200:
            raise NetnsError('at most 200 hosts')
        self.hosts = list(hosts)
        self.rate_mbit = rate_mbit
        self.rates_mbit = dict(rates_mbit or {})
        if set(self.rates_mbit) - set(self.hosts):
            raise NetnsError(f'rates for hosts that are not there: {self.rates_mbit}')
        self.burst_kbit = burst_kbit
        k = next(_made_here)
        self.tag = f'{PREFIX}{os.getpid()}' + (f'x{k}' if k else '')
        self.switch = f'{self.tag}-switch'
        self._procs: list[subprocess.Popen] = []
        self._made: list[str] = []

    # ------------------------------------------------------------------ names
    def ns(self, host: str) -> str:
        """The namespace of `host`."""
        if host not in self.hosts:
            raise NetnsError(f'no host {host!r} (hosts: {self.hosts})')
        return f'{self.tag}-{host}'

    def address(self, host: str) -> str:
        return f'{SUBNET}.{self.hosts.index(host) + 1}'

    def _port(self, host: str) -> str:
        return f'p{self.hosts.index(host) + 1}'

    # ------------------------------------------------------------------ life
    def __enter__(self) -> FieldNetwork:
        if os.geteuid() != 0:
            raise NetnsError('network namespaces need root')
        remove_stale()
        # a SIGTERM (a CI job's timeout, `kill`) unwinds through close() like an exception
        self._old_term = None
        if threading.current_thread() is threading.main_thread() and \
                signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
            self._old_term = signal.signal(signal.SIGTERM, _terminate)
        try:
            self._build()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _build(self) -> None:
        _ip('ip', 'netns', 'add', self.switch)
        self._made.append(self.switch)
        sw = self.switch
        _ip('ip', 'link', 'set', 'lo', 'up', ns=sw)
        _ip('ip', 'link', 'add', 'br0', 'type', 'bridge', 'mcast_snooping', '0', ns=sw)
        _ip('ip', 'link', 'set', 'br0', 'up', ns=sw)
        for host in self.hosts:
            ns, port = self.ns(host), self._port(host)
            _ip('ip', 'netns', 'add', ns)
            self._made.append(ns)
            _ip('ip', 'link', 'set', 'lo', 'up', ns=ns)
            # made inside the host, its peer moved to the switch: no name in the root namespace
            _ip('ip', 'link', 'add', 'eth0', 'type', 'veth', 'peer', 'name', port, ns=ns)
            _ip('ip', 'link', 'set', port, 'netns', sw, ns=ns)
            _ip('ip', 'addr', 'add', f'{self.address(host)}/24', 'dev', 'eth0', ns=ns)
            _ip('ip', 'link', 'set', 'eth0', 'up', ns=ns)
            _ip('ip', 'route', 'add', '224.0.0.0/4', 'dev', 'eth0', ns=ns)
            _ip('ip', 'link', 'set', port, 'master', 'br0', ns=sw)
            _ip('ip', 'link', 'set', port, 'up', ns=sw)
            rate = self.rates_mbit.get(host, self.rate_mbit)
            if rate is not None:
                self.shape(host, rate)

    def close(self) -> None:
        """Stop every process started in the hosts, delete the namespaces (idempotent)."""
        for p in self._procs:
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGTERM)
        t_end = time.monotonic() + 10.0
        for p in self._procs:
            try:
                p.wait(max(0.1, t_end - time.monotonic()))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait(5.0)
        for ns in reversed(self._made):
            _delete(ns)
        self._made.clear()
        if getattr(self, '_old_term', None) is not None:
            signal.signal(signal.SIGTERM, self._old_term)
            self._old_term = None

    # ------------------------------------------------------------------ links
    def shape(self, host: str, rate_mbit: float) -> None:
        """Limit `host`'s link to rate_mbit each way (tbf on both ends)."""
        if not rate_mbit > 0:
            raise NetnsError(f'rate {rate_mbit} Mbit/s')
        for dev, ns in (('eth0', self.ns(host)), (self._port(host), self.switch)):
            _ip('tc', 'qdisc', 'replace', 'dev', dev, 'root', 'tbf', 'rate',
                f'{rate_mbit * 1000:.0f}kbit', 'burst', f'{self.burst_kbit:.0f}kbit',
                'latency', '200ms', ns=ns)

    def cut(self, host: str) -> None:
        """Take `host`'s link down (both ways) until `restore`."""
        _ip('ip', 'link', 'set', self._port(host), 'down', ns=self.switch)

    def restore(self, host: str) -> None:
        _ip('ip', 'link', 'set', self._port(host), 'up', ns=self.switch)

    def link_bytes(self) -> dict[str, dict[str, int]]:
        """Per host: bytes it has `sent` and `received` over its link (counted at the switch)."""
        r = _ip('ip', '-s', '-j', 'link', 'show', ns=self.switch)
        by_port = {d['ifname']: d['stats64'] for d in json.loads(r.stdout)}
        out = {}
        for host in self.hosts:
            st = by_port[self._port(host)]
            # the switch's port receives what the host sends
            out[host] = {'sent': int(st['rx']['bytes']), 'received': int(st['tx']['bytes'])}
        return out

    # ------------------------------------------------------------------ processes
    def ros_env(self, *, domain_id: int, base: Mapping[str, str] | None = None) -> dict[str, str]:
        """An environment for ROS 2 processes on these hosts: `base` (default: this one's) with
        the domain id, discovery over the subnet and the UDP-only Fast DDS profile."""
        env = dict(os.environ if base is None else base)
        env.update(ROS_DOMAIN_ID=str(domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE='SUBNET',
                   FASTRTPS_DEFAULT_PROFILES_FILE=str(UDP_PROFILE))
        env.pop('ROS_STATIC_PEERS', None)
        return env

    def start(self, host: str, argv: Sequence[str], *, env: Mapping[str, str] | None = None,
              log: IO | Path | None = None, cwd: str | Path | None = None
              ) -> subprocess.Popen:
        """Run `argv` on `host` (its own process group; stopped by `close`). `log`: a file or
        path that takes stdout and stderr."""
        with contextlib.ExitStack() as stack:
            out: IO | int = subprocess.DEVNULL if log is None else log if not isinstance(
                log, Path) else stack.enter_context(open(log, 'ab'))  # the child keeps a copy
            p = subprocess.Popen(['ip', 'netns', 'exec', self.ns(host), *argv],
                                 env=dict(env) if env is not None else None, stdout=out,
                                 stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, cwd=cwd,
                                 start_new_session=True)
        self._procs.append(p)
        return p
