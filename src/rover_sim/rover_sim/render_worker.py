"""A second process that renders one eye of the stereo pair while the simulator renders the other.

PyBullet's TinyRenderer holds the GIL for the whole image, and a 640x480 pair of the insertion
site is most of a rendered simulation step; the second core of a small machine sits idle while
the simulator draws. The worker holds a copy of the same world (built from the same config and
truths, so the same site, obstacles, textures and rovers), poses its rovers as the simulator's
are at the moment of the picture, and draws the right eye: the pair is pixel for pixel what one
process draws (test_sim_world), in about the time of one image. No rclpy.
"""
from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import threading
from collections.abc import Sequence
from typing import IO, Any, BinaryIO

import numpy as np

from .config import SimConfig
from .errors import SimError

#: a first image waits for the worker to start and build its world
FIRST_IMAGE_TIMEOUT_S = 120.0
IMAGE_TIMEOUT_S = 30.0


class RenderWorkerError(SimError):
    """The render worker failed or stopped answering; the message says how."""


def _send(stream: IO[bytes], obj: Any) -> None:
    pickle.dump(obj, stream, protocol=pickle.HIGHEST_PROTOCOL)
    stream.flush()


def serve(inp: BinaryIO, out: BinaryIO) -> None:
    """The worker's loop: (config, truths) first, then (poses, eye position, rotation, offset)
    in, an image (or an error string) out; None or the end of the input ends it."""
    from .world import World  # noqa: PLC0415 - world imports this module
    try:
        config, truths = pickle.load(inp)
    except EOFError:                      # the simulator ended before it sent the scene
        return
    world = World(config.replace(render_workers=0), truths)
    try:
        while True:
            try:
                msg = pickle.load(inp)
            except EOFError:
                break
            if msg is None:
                break
            poses, pos, rot, offset = msg
            try:
                world.set_poses(poses)
                image = world.render_eye(pos, rot, offset)
            except Exception as exc:  # noqa: BLE001 - sent back, raised in the simulator
                _send(out, f'{type(exc).__name__}: {exc}')
            else:
                _send(out, image)
    finally:
        world.close()


#: the worker's command: SIGINT ignored first, then the module run as `python -m` would
_START = ('import signal; signal.signal(signal.SIGINT, signal.SIG_IGN); import runpy; '
          "runpy.run_module('rover_sim.render_worker', run_name='__main__', alter_sys=True)")


class RenderWorker:
    """The worker process of one World (`python -m rover_sim.render_worker`, pickles over its
    standard input and output); `request`, then `result`."""

    def __init__(self, config: SimConfig, truths: Sequence[Any]) -> None:
        # SIGINT ignored before the module's imports: a Ctrl-C to the simulator's process group
        # that comes while the worker is still importing numpy and PyBullet would otherwise
        # end it with a traceback (main ignores it too late for that)
        self._proc = subprocess.Popen(
            [sys.executable, '-c', _START], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, start_new_session=False)
        assert self._proc.stdin is not None and self._proc.stdout is not None     # PIPE
        self._stdin: IO[bytes] = self._proc.stdin
        self._stdout: IO[bytes] = self._proc.stdout
        self._first = True
        self._reply: list = []
        self._got = threading.Event()
        try:
            _send(self._stdin, (config, list(truths)))
        except OSError as exc:
            self.close()
            raise RenderWorkerError(f'render worker gone at its start: {exc}') from exc

    def request(self, poses: list, pos: np.ndarray, rot: np.ndarray, offset: float) -> None:
        """Ask for one image (render_eye's arguments, with the rovers' poses)."""
        self._got.clear()
        self._reply = []
        try:
            _send(self._stdin, (poses, np.asarray(pos, float), np.asarray(rot, float),
                                     float(offset)))
        except (OSError, ValueError) as exc:
            raise RenderWorkerError(f'render worker gone: {exc}') from exc
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        try:
            self._reply.append(pickle.load(self._stdout))
        except (EOFError, OSError, pickle.UnpicklingError) as exc:
            self._reply.append(f'the worker ended ({type(exc).__name__}), exit code '
                               f'{self._proc.poll()}')
        self._got.set()

    def result(self) -> np.ndarray:
        """The image asked for; RenderWorkerError if the worker failed or gave none in time."""
        timeout = FIRST_IMAGE_TIMEOUT_S if self._first else IMAGE_TIMEOUT_S
        if not self._got.wait(timeout):
            raise RenderWorkerError(f'render worker gave no image in {timeout:g} s')
        msg = self._reply[0]
        if isinstance(msg, str):
            raise RenderWorkerError(f'render worker: {msg}')
        self._first = False
        return msg

    def close(self) -> None:
        try:
            _send(self._stdin, None)
            self._stdin.close()
        except (OSError, ValueError):
            pass
        try:
            self._proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait(timeout=5.0)
        self._stdout.close()


def main() -> None:
    """The worker process: render the requested eye for each scene on standard input."""
    # the simulator's Ctrl-C ends its input: the worker stops with it, not before it
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # the images go out on a copy of standard output; whatever C or Python code prints (PyBullet
    # does) goes to standard error, where it cannot break the stream
    out = os.fdopen(os.dup(1), 'wb')
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    serve(sys.stdin.buffer, out)


if __name__ == '__main__':
    main()
