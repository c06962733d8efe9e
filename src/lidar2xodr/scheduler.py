"""Where the per-scan work runs: a process pool on this machine, or a Dask cluster.

`task_runner(job, workers, scheduler)` yields `submit(fn, *args)`, which runs `fn(job, *args)`
on a worker and returns a future with `.result()`. The caller takes results in submission
order, so the output is the same bytes whichever runner ran the tasks.

- `scheduler=None` (default): a fork-based `ProcessPoolExecutor` of `workers` processes. It
  starts in milliseconds, the workers inherit the job without pickling it, and they die with
  the build (`lifetime.die_with_parent`), so a kill or Ctrl-C leaves no process behind.
- `scheduler="local"`: a `dask.distributed.LocalCluster` of `workers` single-threaded worker
  processes on this machine (the Dask dashboard and diagnostics, no cluster needed).
- `scheduler="tcp://host:8786"` (any Dask address): an existing `dask.distributed` scheduler.
  Its workers need the same lidar2xodr installed and must see the drive's files at the same
  path (a shared file system); the job (reader, configuration, GNSS poses) is sent to every
  worker once, and only the scans' marking points come back.

The process pool stays the default: on one machine Dask adds seconds of start-up and spawned
interpreters for no gain, and the pool's kill semantics are tested (`tests/test_hostile.py`).
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from lidar2xodr.errors import InputError

_ADDRESS = re.compile(r"^(tcp|tls|ws|wss|ucx|inproc)://\S+$")

_JOB: Any = None


def valid_scheduler(value: str | None) -> str | None:
    """None, 'local' or a Dask scheduler address; anything else is a configuration error."""
    if value is None or value == "local" or _ADDRESS.match(value):
        return value
    raise ValueError(f"scheduler must be 'local' or a Dask address such as tcp://host:8786, not {value!r}")


def _pool_init(job: Any, parent_pid: int) -> None:
    """A pool worker: dies with the build; Ctrl-C and SIGTERM (sent to the whole group) are the parent's."""
    import signal

    from lidar2xodr.lifetime import die_with_parent

    global _JOB
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    die_with_parent(parent_pid)
    _JOB = job


def _pool_call(fn: Callable[..., Any], *args: Any) -> Any:
    return fn(_JOB, *args)


@contextmanager
def task_runner(job: Any, workers: int, scheduler: str | None) -> Iterator[Callable[..., Any]]:
    """`submit(fn, *args)` running `fn(job, *args)` on the chosen workers (see the module docstring)."""
    if scheduler is None:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("fork"), initializer=_pool_init,
                                 initargs=(job, os.getpid())) as pool:
            yield lambda fn, *args: pool.submit(_pool_call, fn, *args)
        return
    with dask_client(scheduler, workers) as client:
        shared = client.scatter(job, broadcast=True, hash=False)
        yield lambda fn, *args: client.submit(fn, shared, *args, pure=False)


def _background_main(send: Any, parent_pid: int, fn: Callable[..., Any], args: tuple[Any, ...]) -> None:
    """The background process: runs fn(*args) and sends ("ok", value), ("input", (where, problem)) or
    ("error", text) back: an InputError keeps its file and problem, any other error its text."""
    _pool_init(None, parent_pid)
    try:
        out: tuple[str, Any] = ("ok", fn(*args))
    except InputError as exc:
        out = ("input", (exc.where, exc.problem))
    except Exception as exc:  # noqa: BLE001 - a bug in fn is the parent's to report
        out = ("error", f"{type(exc).__name__}: {exc}")
    send.send(out)
    send.close()


@contextmanager
def in_background(fn: Callable[..., Any], *args: Any) -> Iterator[Callable[[], Any]]:
    """Start fn(*args) in a forked process now; yield `result()`, which waits for it and returns its
    value (or raises its InputError, or a RuntimeError naming another error). The process inherits the
    arguments without pickling them, dies with the build, and is killed when the block is left
    without taking its result (an error elsewhere need not wait for it).

    The build's lanes stage runs on one core: work that does not depend on it (the object tracks'
    smoothing) runs beside it on the others instead of after it."""
    import multiprocessing as mp

    ctx = mp.get_context("fork")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_background_main, args=(send, os.getpid(), fn, args))
    proc.start()
    send.close()

    def result() -> Any:
        try:
            kind, value = recv.recv()
        except EOFError:
            proc.join()
            raise RuntimeError(f"the background process ended without a result (exit code {proc.exitcode})") from None
        proc.join()
        if kind == "input":
            raise InputError(*value)
        if kind == "error":
            raise RuntimeError(value)
        return value

    try:
        yield result
    finally:
        if proc.is_alive():
            proc.kill()
        proc.join()
        recv.close()


@contextmanager
def dask_client(scheduler: str, workers: int) -> Iterator[Any]:
    """A `distributed.Client`: of a new LocalCluster ('local') or connected to the scheduler at an address."""
    from distributed import Client, LocalCluster

    if scheduler == "local":
        with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                          silence_logs=logging.ERROR) as cluster, Client(cluster) as client:
            yield client
        return
    try:
        client = Client(scheduler, timeout="10s")
    except (OSError, TimeoutError) as exc:
        raise InputError(scheduler, f"cannot reach the Dask scheduler ({exc})") from None
    with client:
        try:
            client.wait_for_workers(1, timeout=30)
        except TimeoutError:
            raise InputError(scheduler, "the Dask scheduler has had no worker for 30 s") from None
        yield client
