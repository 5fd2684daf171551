"""Writing results safely: a file appears whole or not at all; outputs are checked (writable,
a folder where a folder is needed, free space) before the work that fills them, and an
output folder is locked while a run writes into it."""

import errno
import json
import math
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

MB = 1024 * 1024
_UMASK = os.umask(0o022)
os.umask(_UMASK)
# Mode of written files: 0644 under the usual umask 022 (as open() would create them).
FILE_MODE = 0o666 & ~_UMASK
LOCK_NAME = ".drake-rus.lock"


class OutputError(ValueError):
    """An output path cannot be used; the message names the argument (``--out``)."""


@contextmanager
def atomic_path(path: str | Path):
    """Yields a temporary path beside ``path``; renames it onto ``path`` on success.

    On any exception the temporary file is removed and ``path`` is left untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, FILE_MODE)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Writes ``text`` atomically; a ``.json`` file is kept strict JSON (NaN -> null)."""
    if str(path).endswith(".json"):
        text = strict_json_text(text)
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def save_figure(fig, path: str | Path, dpi: int = 110) -> Path:
    """Saves a matplotlib figure as PNG atomically and closes it."""
    import matplotlib.pyplot as plt
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    plt.close(fig)
    return Path(path)


# ------------------------------------------------------------------------ strict JSON
def _finite_or_none(obj):
    """``obj`` with every NaN or infinite float replaced by None (JSON null)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite_or_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite_or_none(v) for v in obj]
    return obj


def dumps_strict(obj, **kwargs) -> str:
    """``json.dumps`` that writes valid JSON: NaN and infinities become null (numpy scalars
    and arrays through ``default``, if given, are converted first)."""
    default = kwargs.pop("default", None)
    if default is not None:
        obj = json.loads(json.dumps(obj, default=default))   # numpy -> Python values
    return json.dumps(_finite_or_none(obj), allow_nan=False, **kwargs)


def strict_json_text(text: str) -> str:
    """``text`` (JSON) unchanged if it is valid JSON; if it holds NaN or Infinity (Python's
    json extension, not JSON), re-written with those values as null."""
    bad = []
    try:
        obj = json.loads(text, parse_constant=lambda c: bad.append(c))
    except ValueError:
        return text          # not JSON at all: the caller's business
    if not bad:
        return text
    return json.dumps(_finite_or_none(obj), indent=2, allow_nan=False) + "\n"


# ------------------------------------------------------------------------ output checks
def _existing_ancestor(path: Path) -> Path:
    p = path.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def _probe_write(folder: Path) -> None:
    """Creates and removes a file in ``folder``: raises OSError if it cannot be written
    (permission bits do not stop root, a read-only file system does)."""
    fd, tmp = tempfile.mkstemp(prefix=".drake-rus-probe-", dir=folder)
    os.close(fd)
    os.unlink(tmp)


def _why(e: OSError) -> str:
    return e.strerror or type(e).__name__


def _check_folder_writable(folder: Path, arg: str, need_bytes: int) -> None:
    if not folder.is_dir():
        raise OutputError(f"{arg}: {folder} is a file, not a folder")
    try:
        _probe_write(folder)
    except OSError as e:
        raise OutputError(f"{arg}: cannot write in {folder} ({_why(e)})") from None
    if need_bytes > 0:
        try:
            free = shutil.disk_usage(folder).free
        except OSError:
            return
        if free < need_bytes:
            raise OutputError(
                f"{arg}: not enough free space in {folder}: {free / MB:.1f} MB free, this "
                f"run writes about {need_bytes / MB:.0f} MB")


def check_output_dir(path, arg: str = "--out", need_bytes: int = 0) -> Path:
    """Checks, without creating anything, that ``path`` can be (or is) a writable folder with
    about ``need_bytes`` free; raises OutputError naming ``arg`` otherwise."""
    path = Path(path)
    if str(path).strip() == "":
        raise OutputError(f"{arg}: expected a folder name, got an empty string")
    if path.exists() and not path.is_dir():
        raise OutputError(f"{arg}: {path} exists and is a file; expected a folder")
    _check_folder_writable(_existing_ancestor(path), arg, need_bytes)
    return path


def check_output_file(path, arg: str, need_bytes: int = 0,
                      suffixes: tuple[str, ...] = ()) -> Path:
    """Checks, without creating anything, that ``path`` can be written as a file (not a
    folder; its folder writable, ``need_bytes`` free; a suffix among ``suffixes``)."""
    path = Path(path)
    if str(path).strip() == "" or path.name in ("", ".", ".."):
        raise OutputError(f"{arg}: expected a file name, got {str(path)!r}")
    if path.is_dir():
        raise OutputError(f"{arg}: {path} is a folder; expected a file name")
    if suffixes and not any(str(path).lower().endswith(s) for s in suffixes):
        raise OutputError(f"{arg}: expected a file name ending in {' or '.join(suffixes)}, "
                          f"got {path}")
    _check_folder_writable(_existing_ancestor(path.parent), arg, need_bytes)
    return path


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@contextmanager
def output_dir(path, arg: str = "--out", need_bytes: int = 0, what: str = "drake-rus"):
    """Checks ``path`` (see :func:`check_output_dir`), creates it and holds a lock file in it
    for the duration: a second run into the same folder is refused (OutputError naming
    ``arg``). On an exception the lock is removed and the folders this call created are
    removed again if nothing was written into them: no empty output folders."""
    path = check_output_dir(path, arg, need_bytes)
    created = []
    p = path.absolute()
    while not p.exists():
        created.append(p)
        p = p.parent
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{arg}: cannot create {path} ({_why(e)})") from None
    lock = path / LOCK_NAME
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            try:
                pid = int(lock.read_text().split()[0])
            except (OSError, ValueError, IndexError):
                pid = -1
            if pid > 0 and _pid_alive(pid):
                raise OutputError(
                    f"{arg}: {path} is in use by another run ({what}, process {pid}); wait "
                    f"for it to finish or choose another {arg}") from None
            lock.unlink(missing_ok=True)       # stale: its process is gone
            continue
        except OSError as e:
            _remove_empty(created)
            raise OutputError(f"{arg}: cannot write in {path} ({_why(e)})") from None
        with os.fdopen(fd, "w") as f:
            f.write(f"{os.getpid()} {what}\n")
        break
    try:
        yield path
    except BaseException:
        lock.unlink(missing_ok=True)
        _remove_empty(created)
        raise
    lock.unlink(missing_ok=True)
    _remove_empty(created)


def _remove_empty(folders) -> None:
    for f in folders:                  # deepest first
        try:
            f.rmdir()
        except OSError:
            break


def argument_for_path(args, filename) -> str | None:
    """The command-line argument (``--out``) whose path ``filename`` lies in, if any."""
    if not filename:
        return None
    target = os.path.abspath(str(filename))
    for name, value in sorted(vars(args).items()):
        if isinstance(value, str) and value and name not in ("command", "func"):
            v = os.path.abspath(value)
            if target == v or target.startswith(v.rstrip(os.sep) + os.sep):
                return "--" + name.replace("_", "-")
    return None


def describe_os_error(e: OSError, args=None) -> str:
    """One line for an OSError, naming the argument whose path failed when it can."""
    where = getattr(e, "filename", None)
    arg = argument_for_path(args, where) if args is not None else None
    if e.errno == errno.ENOSPC:
        text = f"no space left on the device writing {where}"
    elif e.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        text = f"cannot write {where} ({_why(e)})"
    else:
        text = f"{_why(e)}: {where}" if where else str(e)
    return f"{arg}: {text}" if arg else text
