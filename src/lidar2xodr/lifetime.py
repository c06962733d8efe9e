"""Process lifetime: SIGTERM is an interrupt like Ctrl-C, and every process we start dies with us.

`timeout`, CI runners and container stops send SIGTERM; `terminate_as_interrupt` turns it into
`Terminated` (a KeyboardInterrupt), so the same clean-up runs: temporary outputs are removed and
every child started with `run_child` is killed (`children_killed_on_exit`), also where a thread of
ours is the one waiting for it. A SIGKILL runs no clean-up at all, so the
extraction's worker processes and the checker/reader subprocesses ask the kernel to kill them
when their parent dies (Linux `prctl(PR_SET_PDEATHSIG)`, see `dying_with_us`), and the next run removes the dead
run's temporary folders (`fileio.clean_stale`).
"""

from __future__ import annotations

import contextlib
import ctypes
import io
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor
from types import FrameType
from typing import Any

_PR_SET_PDEATHSIG = 1
try:
    _LIBC: ctypes.CDLL | None = ctypes.CDLL(None, use_errno=True)  # this process's libc (no lookup after fork)
    _PRCTL = _LIBC.prctl
except (OSError, AttributeError):
    _PRCTL = None


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived: handled like Ctrl-C, reported with exit code 143 (128 + SIGTERM)."""


_SIGNALLED: list[int | None] = [None]  # the SIGTERM/SIGINT that arrived in the current `terminate_as_interrupt` block
_STDERR: list[Any] = [None]  # the real sys.stderr while it is muted after a signal
_RECEIVED: list[int | None] = [None]  # the one that arrived in the latest block, kept after it


def _interrupt(signum: int) -> KeyboardInterrupt:
    return Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def _on_signal(signum: int, frame: FrameType | None) -> None:
    """Record the signal, kill our children, raise the interrupt.

    The raise alone is not enough: when the signal lands in a finaliser or weakref callback, Python
    prints "Exception ignored" and goes on, and a main thread waiting for a checker thread would
    wait for it up to its timeout (a CI run saw `check` ignore a SIGTERM this way). The record and
    the killed children make the waiting thread raise instead (`raise_if_signalled`).
    """
    _SIGNALLED[0] = _RECEIVED[0] = signum
    _mute_stderr()
    kill_children()
    raise _interrupt(signum)


def _mute_stderr() -> None:
    """Drop what is written to sys.stderr until the block ends: code the interrupt unwinds may print
    before it re-raises (CI: scipy's decorator printed "Error in generated code:" and the source of
    the function it was making), and the command's own line, printed after the block, is the one
    line the user sees."""
    if _STDERR[0] is None:
        _STDERR[0] = sys.stderr
        sys.stderr = io.StringIO()


def _unmute_stderr() -> None:
    if _STDERR[0] is not None:
        sys.stderr = _STDERR[0]
        _STDERR[0] = None


def terminated() -> bool:
    """Whether a SIGTERM arrived: the `Terminated` it raised can come out as another error (a C
    extension being imported at that moment reports "ImportError: initialization failed")."""
    return _RECEIVED[0] == signal.SIGTERM


def raise_if_signalled() -> None:
    """Raise the interrupt of a SIGTERM/SIGINT that arrived in this block, also where its own raise was lost.

    Called where work resumes after waiting for a child, and before an output is moved into place.
    """
    if _SIGNALLED[0] is not None:
        raise _interrupt(_SIGNALLED[0])


def _quiet_interrupts(previous: Callable[[Any], object]) -> Callable[[Any], None]:
    """An unraisable hook that drops our own lost interrupts (they are recorded) and passes on the rest."""
    def hook(unraisable: Any) -> None:
        if isinstance(unraisable.exc_value, KeyboardInterrupt) and _SIGNALLED[0] is not None:
            return
        previous(unraisable)
    return hook


@contextlib.contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM raises `Terminated` and SIGINT `KeyboardInterrupt` in the main thread, and
    both kill the children of `run_child` (elsewhere: no change; an ignored SIGINT stays ignored)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _SIGNALLED[0] = _RECEIVED[0] = None
    previous = {signal.SIGTERM: signal.signal(signal.SIGTERM, _on_signal)}
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        previous[signal.SIGINT] = signal.signal(signal.SIGINT, _on_signal)
    hook = sys.unraisablehook
    sys.unraisablehook = _quiet_interrupts(hook)
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        sys.unraisablehook = hook
        _SIGNALLED[0] = None
        _unmute_stderr()


def die_with_parent(parent_pid: int | None = None) -> None:
    """Ask the kernel to SIGKILL this process when its parent dies (Linux; elsewhere a no-op).

    Called first thing in a pool worker; `parent_pid` guards the race
    where the parent died before the request was made.
    """
    if _PRCTL is None:
        return
    _PRCTL(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    if parent_pid is not None and os.getppid() != parent_pid:
        os._exit(1)


_EXEC_FAILED = "lidar2xodr: exec failed, errno "
_LAUNCHER = (
    "import ctypes, os, sys\n"
    f"ctypes.CDLL(None).prctl({_PR_SET_PDEATHSIG}, {int(signal.SIGKILL)}, 0, 0, 0)\n"
    "if os.getppid() != int(sys.argv[1]):\n    os._exit(1)\n"
    "try:\n    os.execvp(sys.argv[2], sys.argv[2:])\n"
    f"except OSError as exc:\n    os.write(2, b'{_EXEC_FAILED}%d\\n' % exc.errno)\n    os._exit(127)\n"
)


def dying_with_us(cmd: Sequence[str]) -> list[str]:
    """`cmd` started through a launcher that asks the kernel to kill it when this process dies.

    The request cannot be a `preexec_fn`: Python then forks instead of vforking, which runs the
    at-fork handlers of every library in this process, and OpenBLAS's stops its thread pool
    under a BLAS call of the main thread, which never returns (a `check` spawns its readers from
    threads while the main thread measures the map: a CI build hung in it and ignored SIGTERM).
    The launcher (a bare Python) makes the request, then replaces itself with `cmd` (same pid).
    """
    if _PRCTL is None:
        return list(cmd)
    return [sys.executable, "-I", "-S", "-c", _LAUNCHER, str(os.getpid()), *cmd]


_CHILDREN: set[subprocess.Popen[str]] = set()
_CHILDREN_LOCK = threading.RLock()  # re-entered by the signal handler in the main thread
_STOPPING = [0]  # > 0 while a block of `children_killed_on_exit` is being left by an exception


def run_child(cmd: Sequence[str], *, timeout: float, env: dict[str, str] | None = None,
              cwd: str | os.PathLike[str] | None = None) -> subprocess.CompletedProcess[str]:
    """`subprocess.run(cmd, capture_output=True, text=True)` for a child that dies with us.

    The child is registered while it runs, so `kill_children` can end it from the main thread
    while a worker thread waits for it (an interrupted `check` must not wait up to `timeout`
    for a checker that nobody reads any more).
    """
    with subprocess.Popen(dying_with_us(cmd), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                          cwd=cwd) as proc:
        with _CHILDREN_LOCK:
            _CHILDREN.add(proc)
            if _STOPPING[0] or _SIGNALLED[0] is not None:
                proc.kill()
        try:
            out, err = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            raise
        finally:
            with _CHILDREN_LOCK:
                _CHILDREN.discard(proc)
    raise_if_signalled()
    if proc.returncode == 127 and err.startswith(_EXEC_FAILED):
        code = int(err[len(_EXEC_FAILED):].split()[0])
        raise OSError(code, os.strerror(code), cmd[0])
    return subprocess.CompletedProcess(list(cmd), proc.returncode, out, err)


def kill_children() -> None:
    """SIGKILL every child of `run_child` that still runs."""
    with _CHILDREN_LOCK:
        running = list(_CHILDREN)
    for proc in running:
        with contextlib.suppress(OSError):
            proc.kill()


@contextlib.contextmanager
def children_killed_on_exit(pool: Executor | None = None) -> Iterator[None]:
    """Leaving the block by an exception (Ctrl-C, SIGTERM, an error) kills the children it started.

    With `pool`, its threads are waited for here, and every child they start meanwhile is killed at
    once: a thread that runs two children in a row (netconvert's `--version`, then the conversion)
    must not start the second one after the first was killed, nor keep the exit waiting for it.
    """
    try:
        yield
    except BaseException:
        with _CHILDREN_LOCK:
            _STOPPING[0] += 1
        try:
            kill_children()
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)
        finally:
            with _CHILDREN_LOCK:
                _STOPPING[0] -= 1
        raise
