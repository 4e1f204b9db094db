"""PyBullet import and client handling: one place for the simulator's global quirks.

PyBullet prints a build banner when it is first imported; :func:`import_pybullet` swallows it so
command-line output stays readable. Clients are always explicit (``physicsClientId``): no global handle.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys

_pybullet = None


def _libc_fflush() -> None:
    try:
        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError):
        pass


@contextlib.contextmanager
def silenced_output():
    """Send the C-level stdout and stderr (file descriptors 1 and 2) to /dev/null for the duration of the block.
    PyBullet's C code prints its banner on either, through the C library's buffers."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), 1)
            os.dup2(devnull.fileno(), 2)
            yield
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        _libc_fflush()  # flush the C library's buffers while they still go nowhere
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in saved:
            os.close(fd)


def import_pybullet():
    """Import and return the ``pybullet`` module without its banner on stdout."""
    global _pybullet
    if _pybullet is None:
        with silenced_output():
            import pybullet

        _pybullet = pybullet
    return _pybullet


class BulletClient:
    """A PyBullet DIRECT (headless) client, disconnected on ``close()`` or at the end of a ``with`` block."""

    def __init__(self) -> None:
        self.pb = import_pybullet()
        with silenced_output():
            self.client_id = self.pb.connect(self.pb.DIRECT)
        if self.client_id < 0:
            raise RuntimeError("could not start a PyBullet DIRECT client")

    def close(self) -> None:
        if self.client_id >= 0:
            self.pb.disconnect(physicsClientId=self.client_id)
            self.client_id = -1

    def __enter__(self) -> BulletClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:  # best effort; explicit close() is preferred
        try:
            self.close()
        except Exception:
            pass
