"""Atomic output: everything is written to a temporary sibling and renamed into place.

A crash or a rejected result never leaves a half-written map, cloud or report behind:
- `atomic_path` / `atomic_dir` write a temporary sibling and rename it onto the target on success.
- Inside `staged_outputs()` those renames wait until the whole command succeeded, so a command
  that fails writes none of its outputs (`staged(target)` finds a staged file's temporary copy).
- A folder we write (a report, a simulated drive) carries a marker file listing the files we
  wrote. An existing folder is replaced only when it is empty or carries our marker, and then
  only our files are replaced or removed: a file of the user's in it is never touched.
- Temporary names carry our process id (`.lidar2xodr-PID-...`), so `clean_stale` removes the
  leftovers of a killed run (its pid is dead) when the next run starts.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from lidar2xodr.errors import OutputError
from lidar2xodr.lifetime import raise_if_signalled


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _umask()
_STALE_HIDDEN = re.compile(r"^\.lidar2xodr-(?:[a-z]+-)?(\d+)-")
_STALE_SYSTEM = re.compile(r"^lidar2xodr-(?:[a-z]+-)?(\d+)-")


def marker_name(kind: str) -> str:
    """The file that marks a folder as one of ours (`.lidar2xodr-report`, `.lidar2xodr-drive`)."""
    return f".lidar2xodr-{kind}"


def temp_prefix(kind: str = "", hidden: bool = True) -> str:
    """Prefix of our temporary files and folders; the pid lets a later run recognise a dead run's leftovers."""
    return f"{'.' if hidden else ''}lidar2xodr-{kind + '-' if kind else ''}{os.getpid()}-"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def clean_stale(folder: str | Path) -> list[Path]:
    """Remove our temporary files and folders in `folder` whose owning process is dead; return them.

    Beside the user's outputs only hidden names of ours (`.lidar2xodr-PID-...`) are touched; the
    unhidden form is ours only in the system's temporary folder (a user's `lidar2xodr-2024-runs/`
    next to a map is theirs).
    """
    removed: list[Path] = []
    try:
        entries = list(Path(folder).iterdir())
        system = Path(folder).resolve() == Path(tempfile.gettempdir()).resolve()
    except OSError:
        return removed
    pattern = _STALE_SYSTEM if system else _STALE_HIDDEN
    for entry in entries:
        m = pattern.match(entry.name)
        if m is None or int(m.group(1)) == os.getpid() or _pid_alive(int(m.group(1))):
            continue
        try:
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            else:
                entry.unlink()
            removed.append(entry)
        except OSError:
            continue
    return removed


def os_problem(exc: OSError) -> str:
    """What went wrong, in words a user acts on (a full disk, a read-only file system, permissions)."""
    if exc.errno == errno.ENOSPC:
        return "no space left on the device"
    if exc.errno == errno.EROFS:
        return "the file system is read-only"
    if exc.errno in (errno.EACCES, errno.EPERM):
        return "permission denied (read-only or immutable target?)"
    return exc.strerror or str(exc)


def _followed(target: Path) -> Path:
    """The file a symbolic link names (followed to the end; it may not exist yet), else `target`."""
    return Path(os.path.realpath(target)) if target.is_symlink() else target


def check_output_file(target: str | Path) -> Path:
    """Refuse an output file path that is a folder; return it as a Path.

    An output that is a symbolic link is written where the link points, and the link stays (a
    `latest.xodr` link to the day's map gets the new map; replacing the link itself with a file
    would leave the linked map stale)."""
    target = _followed(Path(target))
    if target.is_dir():
        raise OutputError(target, "is a folder, not a file: give the file name to write")
    if target.exists() and not target.is_file():  # the rename would replace a device (/dev/null), pipe or socket
        raise OutputError(target, "is a device, pipe or socket, not a file: give the file name to write")
    if target.parent.exists() and not target.parent.is_dir():
        raise OutputError(target, f"{target.parent} is a file, not a folder")
    return target


def _is_ours(target: Path, kind: str, entries: list[str]) -> bool:
    """A folder with our marker, or a report written before reports had one (its index.html says so)."""
    if marker_name(kind) in entries:
        return True
    if kind == "report" and "index.html" in entries:
        with contextlib.suppress(OSError):
            return "<title>lidar2xodr report</title>" in (target / "index.html").read_text(errors="replace")[:2000]
    return False


def check_output_dir(target: str | Path, kind: str) -> Path:
    """Refuse an output folder that is a file, or a non-empty folder that is not one of our `kind` folders."""
    target = Path(target)
    if target.exists() and not target.is_dir():
        raise OutputError(target, f"is a file, not a folder: give a new or empty folder for the {kind}")
    if target.is_dir():
        try:
            entries = [p.name for p in target.iterdir()]
        except OSError as exc:
            raise OutputError(target, f"cannot read the folder: {os_problem(exc)}") from None
        if entries and not _is_ours(target, kind, entries):
            raise OutputError(target, f"is a folder with files that are not a lidar2xodr {kind} (it has no "
                              f"{kind} marker): give a new or empty folder; nothing was changed")
    return target


def prepare_outputs(files: list[Path | None], folders: list[tuple[Path | None, str]] | None = None) -> None:
    """Refuse unusable outputs before any work (a folder as a file, a foreign folder, two outputs on
    one path); remove a killed run's leftovers beside them."""
    targets: dict[Path, str] = {}
    parents = set()
    named = [(f, None) for f in files] + list(folders or [])
    for path, kind in named:
        if path is None:
            continue
        if kind is None:
            check_output_file(path)
        else:
            check_output_dir(path, kind)
        key = Path(path).resolve()
        if key in targets:
            raise OutputError(path, f"given for two outputs (the {targets[key]} and the {kind or 'file'})")
        targets[key] = kind or "file"
        parents.add(Path(path).parent)
    for key in targets:
        for folder, kind in targets.items():
            if kind != "file" and folder != key and folder in key.parents:
                raise OutputError(key, f"lies inside the {kind} folder {folder}, which this command replaces")
    for parent in parents | {Path(tempfile.gettempdir())}:
        clean_stale(parent)


@dataclass
class _Staged:
    """Renames deferred until the command succeeded: (temporary path, target, folder kind or None)."""

    moves: list[tuple[Path, Path, str | None]] = field(default_factory=list)
    created: list[Path] = field(default_factory=list)


def _make_parents(folder: Path) -> list[Path]:
    """Create `folder` and its missing ancestors; return those created, deepest first."""
    missing = []
    for p in [folder, *folder.parents]:
        if p.exists():
            break
        missing.append(p)
    folder.mkdir(parents=True, exist_ok=True)
    return missing


def _remove_empty(folders: list[Path]) -> None:
    """Remove folders we created for outputs that were never written (deepest first, only if empty)."""
    for p in folders:
        with contextlib.suppress(OSError):
            p.rmdir()


_CURRENT: contextvars.ContextVar[_Staged | None] = contextvars.ContextVar("lidar2xodr_staged", default=None)


@contextlib.contextmanager
def staged_outputs() -> Iterator[None]:
    """Keep every atomic output written inside in its temporary copy; move them all into place at the end.

    On an exception every temporary copy is removed and no target is touched. Nested uses join the
    outermost one.
    """
    if _CURRENT.get() is not None:
        yield
        return
    staged_set = _Staged()
    token = _CURRENT.set(staged_set)
    try:
        yield
        raise_if_signalled()
    except BaseException:
        for tmp, _, _ in staged_set.moves:
            _remove(tmp)
        _remove_empty(sorted(set(staged_set.created), key=lambda p: len(p.parts), reverse=True))
        raise
    finally:
        _CURRENT.reset(token)
    try:
        for tmp, target, kind in staged_set.moves:
            if kind is None:
                _commit_file(tmp, target)
            else:
                _commit_dir(tmp, target, kind)
    finally:
        for tmp, _, _ in staged_set.moves:
            _remove(tmp)


def staged(target: str | Path) -> Path:
    """The path where `target`'s content is now: its temporary copy while staged, else `target` itself."""
    target = _followed(Path(target))
    staged_set = _CURRENT.get()
    if staged_set is not None:
        for tmp, dest, _ in reversed(staged_set.moves):
            if dest == target:
                return tmp
    return target


def _remove(path: Path) -> None:
    """Remove a temporary file of ours (with its private folder) or a temporary folder of ours."""
    if path.parent.name.startswith(temp_prefix()) and not path.is_dir():
        path = path.parent
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists() or path.is_symlink():
        with contextlib.suppress(OSError):
            path.unlink()


def _commit_file(tmp: Path, target: Path) -> None:
    try:
        check_output_file(target)
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, target)
        if tmp.parent.name.startswith(temp_prefix()):
            tmp.parent.rmdir()
    except OSError as exc:
        raise OutputError(target, f"cannot write: {os_problem(exc)}") from None


@contextlib.contextmanager
def atomic_path(target: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary file path next to `target`; rename it onto `target` only on success.

    The temporary file has `target`'s name (in a hidden folder of ours beside it), so whatever
    reads or names it (a checker, a report title) sees the user's file name. `suffix` is added
    when the name does not end with it.
    """
    target = check_output_file(target)
    name = target.name if not suffix or target.name.endswith(suffix) else target.name + suffix
    staged_set = _CURRENT.get()
    tmp_dir, created = _staging_dir(target, staged_set)
    tmp_path = tmp_dir / name
    keep = False
    try:
        try:
            yield tmp_path
        except OSError as exc:
            raise OutputError(target, f"cannot write: {os_problem(exc)}") from None
        if not tmp_path.is_file():
            raise OutputError(target, "nothing was written")
        raise_if_signalled()
        if staged_set is not None:
            staged_set.moves.append((tmp_path, target, None))
            keep = True
        else:
            _commit_file(tmp_path, target)
    finally:
        if not keep:
            _remove(tmp_dir)
            if not target.exists():
                _remove_empty(created)


def _files(folder: Path) -> set[str]:
    return {p.relative_to(folder).as_posix() for p in folder.rglob("*") if not p.is_dir() or p.is_symlink()}


def _ours(target: Path, kind: str) -> set[str]:
    marker = target / marker_name(kind)
    try:
        lines = marker.read_text(encoding="utf-8").splitlines()
    except OSError:
        return set()
    return {ln for ln in lines if ln and not ln.startswith("#")} | {marker_name(kind)}


def _commit_dir(tmp: Path, target: Path, kind: str) -> None:
    """Move the finished folder `tmp` onto `target`, replacing only files we wrote there before."""
    try:
        check_output_dir(target, kind)
        new = _files(tmp)
        (tmp / marker_name(kind)).write_text(
            f"# written by lidar2xodr ({kind}); a re-run replaces these files and no others\n"
            + "".join(f"{name}\n" for name in sorted(new)), encoding="utf-8")
        os.chmod(tmp, 0o777 & ~_UMASK)
        if not target.exists():
            os.replace(tmp, target)
            return
        ours, present = _ours(target, kind), _files(target)
        if present <= ours:
            backup = target.with_name(f"{temp_prefix()}{target.name}.old")
            os.replace(target, backup)
            os.replace(tmp, target)
            shutil.rmtree(backup, ignore_errors=True)
            return
        for name in sorted(new | {marker_name(kind)}):
            dest = target / name
            dest.parent.mkdir(parents=True, exist_ok=True)
            os.replace(tmp / name, dest)
        for name in sorted(ours - new - {marker_name(kind)}):
            with contextlib.suppress(OSError):
                (target / name).unlink()
    except OSError as exc:
        raise OutputError(target, f"cannot write: {os_problem(exc)}") from None



def _staging_dir(target: Path, staged_set: _Staged | None) -> tuple[Path, list[Path]]:
    """A hidden temporary folder of ours beside `target` (its missing parents made and recorded)."""
    created: list[Path] = []
    try:
        created = _make_parents(target.parent)
        if staged_set is not None:
            staged_set.created.extend(created)
        return Path(tempfile.mkdtemp(prefix=f"{temp_prefix()}{target.name}.", dir=target.parent)), created
    except OSError as exc:
        _remove_empty(created)
        raise OutputError(target, f"cannot write: {os_problem(exc)}") from None

@contextlib.contextmanager
def atomic_dir(target: str | Path, kind: str = "report") -> Iterator[Path]:
    """Yield a temporary folder next to `target`; its files replace `target`'s only on success.

    `target` must be new, empty or a folder of ours of this `kind` (see the module docstring).
    """
    target = check_output_dir(target, kind)
    staged_set = _CURRENT.get()
    tmp, created = _staging_dir(target, staged_set)
    keep = False
    try:
        try:
            yield tmp
        except OSError as exc:
            raise OutputError(target, f"cannot write: {os_problem(exc)}") from None
        raise_if_signalled()
        if staged_set is not None:
            staged_set.moves.append((tmp, target, kind))
            keep = True
        else:
            _commit_dir(tmp, target, kind)
    finally:
        if not keep:
            _remove(tmp)
            if not target.exists():
                _remove_empty(created)


@contextlib.contextmanager
def temp_dir(folder: str | Path | None = None, kind: str = "") -> Iterator[Path]:
    """A scratch folder of ours (in `folder`, default the system's), removed at the end; stale ones are cleaned."""
    base = Path(folder) if folder is not None else Path(tempfile.gettempdir())
    clean_stale(base)
    try:
        tmp = Path(tempfile.mkdtemp(prefix=temp_prefix(kind, hidden=folder is not None), dir=base))
    except OSError as exc:
        raise OutputError(base, f"cannot create a temporary folder: {os_problem(exc)}") from None
    try:
        yield tmp
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def write_text(target: str | Path, text: str) -> None:
    with atomic_path(target) as tmp:
        tmp.write_text(text, encoding="utf-8")


def write_bytes(target: str | Path, data: bytes) -> None:
    with atomic_path(target) as tmp:
        tmp.write_bytes(data)
