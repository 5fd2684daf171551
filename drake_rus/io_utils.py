"""Writing results safely: a file appears whole or not at all; outputs are checked (writable,
a folder where a folder is needed, free space) before the work that fills them, and an
output folder is locked while a run writes into it."""

import datetime
import errno
import json
import math
import os
import shlex
import shutil
import sys
import tempfile
import uuid
from contextlib import ExitStack, contextmanager
from pathlib import Path

from drake_rus import interrupts

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

    On any exception (a signal included) the temporary file is removed, and so are the
    folders this call made for ``path`` that are still empty (none other), and ``path`` is
    left untouched; an OSError without a file name (a write that fills the disk) is raised
    again naming ``path``.
    """
    path = Path(path)
    made = _missing_folders(path.parent)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with ExitStack() as stack:
            # Creating the temporary file and taking charge of it is one step for signals.
            with interrupts.deferred(reraise=False):
                fd, tmp = tempfile.mkstemp(
                    prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent
                )
                os.close(fd)
                cleanup = stack.enter_context(_TemporaryFile(tmp))
            interrupts.check()
            try:
                yield Path(tmp)
            except OSError as e:
                if e.errno is not None and e.filename in (None, tmp):
                    raise OSError(e.errno, e.strerror or os.strerror(e.errno), str(path)) from e
                raise
            os.chmod(tmp, FILE_MODE)
            os.replace(tmp, path)
            cleanup.done = True
    except BaseException:
        with interrupts.deferred(reraise=False):
            _remove_empty_folders(made)
        raise


def _missing_folders(folder: Path) -> list[Path]:
    """The folders on the way to ``folder`` (itself included) that do not exist yet,
    deepest first: those a ``mkdir(parents=True)`` of it would make."""
    missing = []
    while not folder.exists() and folder != folder.parent:
        missing.append(folder)
        folder = folder.parent
    return missing


def _remove_empty_folders(folders: list[Path]) -> None:
    """Removes ``folders`` (deepest first) while they are empty; a folder that is not (or
    cannot be removed) is kept, and so are the ones above it."""
    for folder in folders:
        try:
            folder.rmdir()
        except FileNotFoundError:
            continue  # never made (the failure came first)
        except OSError:
            return


@contextmanager
def staged_files(folder: str | Path, prefix: str):
    """Yields a temporary folder inside ``folder`` (created, with its parents, if missing).
    On success every file written into it is renamed into ``folder``, so files that belong
    together (a model and its card) appear whole and together; on any exception nothing is
    left behind: the temporary folder goes, and so does ``folder`` if this call made it."""
    folder = Path(folder)
    created = not folder.exists()
    folder.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=prefix, dir=folder))
    try:
        yield stage
        for f in sorted(stage.iterdir()):
            os.replace(f, folder / f.name)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        if created:
            shutil.rmtree(folder, ignore_errors=True)
        raise
    shutil.rmtree(stage, ignore_errors=True)


class _TemporaryFile:
    """Removes a temporary file unless ``done`` (when the block ends by any exception)."""

    def __init__(self, path):
        self.path, self.done = Path(path), False

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if not self.done:
            with interrupts.deferred(reraise=False):
                self.path.unlink(missing_ok=True)
        return False


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
        obj = json.loads(json.dumps(obj, default=default))  # numpy -> Python values
    return json.dumps(_finite_or_none(obj), allow_nan=False, **kwargs)


def strict_json_text(text: str) -> str:
    """``text`` (JSON) unchanged if it is valid JSON; if it holds NaN or Infinity (Python's
    json extension, not JSON), re-written with those values as null."""
    bad = []
    try:
        obj = json.loads(text, parse_constant=lambda c: bad.append(c))
    except ValueError:
        return text  # not JSON at all: the caller's business
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
                f"run writes about {need_bytes / MB:.0f} MB"
            )


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


def check_output_file(path, arg: str, need_bytes: int = 0, suffixes: tuple[str, ...] = ()) -> Path:
    """Checks, without creating anything, that ``path`` can be written as a file (not a
    folder; its folder writable, ``need_bytes`` free; a suffix among ``suffixes``)."""
    path = Path(path)
    if str(path).strip() == "" or path.name in ("", ".", ".."):
        raise OutputError(f"{arg}: expected a file name, got {str(path)!r}")
    if path.is_dir():
        raise OutputError(f"{arg}: {path} is a folder; expected a file name")
    if suffixes and not any(str(path).lower().endswith(s) for s in suffixes):
        raise OutputError(
            f"{arg}: expected a file name ending in {' or '.join(suffixes)}, got {path}"
        )
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


def _process_start(pid: int) -> int | None:
    """When process ``pid`` started (clock ticks since boot, /proc), to tell it from a later
    process that reuses its number; None where /proc is not available."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return int(f.read().rsplit(")", 1)[1].split()[19])
    except (OSError, ValueError, IndexError):
        return None


def _lock_record(what: str, argv) -> dict:
    """What the lock file says about the run holding it."""
    argv = list(sys.argv if argv is None else argv)
    if argv and os.path.basename(str(argv[0])) in ("cli.py", "drake-rus"):
        argv[0] = "drake-rus"
    pid = os.getpid()
    return {
        "pid": pid,
        "command": what,
        "argv": [str(a) for a in argv],
        "started_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "process_start": _process_start(pid),
        "token": uuid.uuid4().hex,
    }


def read_lock(path) -> dict | None:
    """The lock record of a folder's lock file (``pid``, ``command``, ``argv``,
    ``started_utc``; a lock of an older version holds "PID COMMAND"), None if unreadable."""
    try:
        text = Path(path).read_text()
    except OSError:
        return None
    try:
        record = json.loads(text)
        if isinstance(record, dict) and isinstance(record.get("pid"), int):
            return record
    except ValueError:
        pass
    words = text.split()
    if words and words[0].isdigit():
        return {"pid": int(words[0]), "command": " ".join(words[1:]) or "drake-rus"}
    return None


def _lock_held(record: dict | None) -> bool:
    """True while the process that wrote the lock ``record`` runs."""
    if record is None or record["pid"] <= 0 or not _pid_alive(record["pid"]):
        return False
    started = record.get("process_start")
    now = _process_start(record["pid"])
    return started is None or now is None or started == now


def _describe_holder(record: dict) -> str:
    text = f"drake-rus {record.get('command', '')}".strip() + f", process {record['pid']}"
    started = record.get("started_utc")
    if started:
        try:
            t = datetime.datetime.fromisoformat(started)
            ago = (datetime.datetime.now(datetime.timezone.utc) - t).total_seconds()
            text += f", started {t.strftime('%Y-%m-%d %H:%M:%S')} UTC ({_duration(ago)} ago)"
        except (TypeError, ValueError):
            text += f", started {started}"
    argv = record.get("argv")
    if argv:
        text += ": " + " ".join(shlex.quote(str(a)) for a in argv)
    return text


def _duration(seconds: float) -> str:
    seconds = max(0, int(seconds))
    if seconds < 120:
        return f"{seconds} s"
    if seconds < 7200:
        return f"{seconds // 60} min"
    return f"{seconds // 3600} h {seconds % 3600 // 60} min"


@contextmanager
def output_dir(path, arg: str = "--out", need_bytes: int = 0, what: str = "drake-rus", argv=None):
    """Checks ``path`` (see :func:`check_output_dir`), creates it and holds a lock file in it
    for the duration: a second run into the same folder is refused (OutputError naming
    ``arg`` and the run holding the lock: command, process, start time, its command line
    ``argv``, default ``sys.argv``). On an exception the lock is removed and the folders this
    call created are removed again if nothing was written into them: no empty output
    folders. Signals wait while the lock is taken and released."""
    path = check_output_dir(path, arg, need_bytes)
    created = []
    p = path.absolute()
    while not p.exists():
        created.append(p)
        p = p.parent
    lock = path / LOCK_NAME
    record = _lock_record(what, argv)
    # Every step from taking the lock to releasing it is inside the try, so that a signal at
    # any moment (raised between the steps, never inside one) releases it.
    try:
        with interrupts.deferred(reraise=False):
            _take_lock(path, lock, record, created, arg)
        interrupts.check()
        yield path
        with interrupts.deferred(reraise=False):
            _release_lock(lock, record)
            _remove_empty(created)
    except BaseException:
        with interrupts.deferred(reraise=False):
            _release_lock(lock, record)
            _remove_empty(created)
        raise


def _take_lock(path: Path, lock: Path, record: dict, created: list, arg: str) -> None:
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{arg}: cannot create {path} ({_why(e)})") from None
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            holder = read_lock(lock)
            if _lock_held(holder):
                raise OutputError(
                    f"{arg}: {path} is in use by another run ({_describe_holder(holder)}); "
                    f"wait for it to finish or choose another {arg}"
                ) from None
            lock.unlink(missing_ok=True)  # stale: its process is gone
            continue
        except OSError as e:
            raise OutputError(f"{arg}: cannot write in {path} ({_why(e)})") from None
        with os.fdopen(fd, "w") as f:
            f.write(json.dumps(record) + "\n")
        return
    raise OutputError(f"{arg}: cannot take the lock {lock} (another run keeps taking it)")


def _release_lock(lock: Path, record: dict) -> None:
    """Removes the lock if it is still this run's (not another's that refused this one)."""
    held = read_lock(lock)
    if held is None or held.get("token") == record["token"]:
        lock.unlink(missing_ok=True)


def _remove_empty(folders) -> None:
    for f in folders:  # deepest first
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
        text = "no space left on the device" + (
            f" writing {where}" if where else " (free some space and run again)"
        )
    elif e.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        text = f"cannot write {where} ({_why(e)})" if where else f"cannot write ({_why(e)})"
    else:
        text = f"{_why(e)}: {where}" if where else str(e)
    return f"{arg}: {text}" if arg else text
