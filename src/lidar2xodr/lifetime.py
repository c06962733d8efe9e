"""Process lifetime: SIGTERM is an interrupt like Ctrl-C, and every process we start dies with us.

`timeout`, CI runners and container stops send SIGTERM; `terminate_as_interrupt` turns it into
`Terminated` (a KeyboardInterrupt), so the same clean-up runs: temporary outputs are removed and
running checkers are killed by `subprocess.run`. A SIGKILL runs no clean-up at all, so the
extraction's worker processes and the checker/reader subprocesses ask the kernel to kill them
when their parent dies (Linux `prctl(PR_SET_PDEATHSIG)`), and the next run removes the dead
run's temporary folders (`fileio.clean_stale`).
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import signal
import threading
from collections.abc import Iterator
from types import FrameType

_PR_SET_PDEATHSIG = 1
try:
    _LIBC: ctypes.CDLL | None = ctypes.CDLL(None, use_errno=True)  # this process's libc (no lookup after fork)
    _PRCTL = _LIBC.prctl
except (OSError, AttributeError):
    _PRCTL = None


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived: handled like Ctrl-C, reported with exit code 143 (128 + SIGTERM)."""


def _raise_terminated(signum: int, frame: FrameType | None) -> None:
    raise Terminated()


@contextlib.contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM raises `Terminated` in the main thread (elsewhere: no change)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def die_with_parent(parent_pid: int | None = None) -> None:
    """Ask the kernel to SIGKILL this process when its parent dies (Linux; elsewhere a no-op).

    Called first thing in a worker or (as `preexec_fn`) in a child; `parent_pid` guards the race
    where the parent died before the request was made.
    """
    if _PRCTL is None:
        return
    _PRCTL(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    if parent_pid is not None and os.getppid() != parent_pid:
        os._exit(1)


def child_preexec() -> functools.partial[None]:
    """A `preexec_fn` for our subprocesses: the child dies with this process."""
    return functools.partial(die_with_parent, os.getpid())
