"""Ctrl-C (SIGINT) and SIGTERM for the command line: end at any moment, cleanly.

``drake-rus`` installs :func:`handling` for the whole command. A signal then raises
:class:`Interrupted` (a ``KeyboardInterrupt``, so every ``except KeyboardInterrupt`` and
``finally`` on the way out runs: the hardware session's zero velocity, the removal of
temporary files and of the output folder's lock) and is remembered: code that swallowed the
exception (a library turning it into an ImportError during an import, say) meets it again at
the next :func:`check` (the simulation loop checks after every chunk). The command's exit
status is then ``128 + signal`` (130 for SIGINT, 143 for SIGTERM).

:func:`deferred` holds signals back where being stopped half-way would leave a mess (taking
the output folder's lock, creating a temporary file, writing the INTERRUPTED summary): the
signal is recorded and, with ``reraise``, raised when the block ends. During the start-up
imports (:func:`importing`) a signal is recorded by the handler and raised at the next
``import`` statement (a ``sys.meta_path`` checkpoint), not inside a module's initialisation,
where libraries swallow it or turn it into an ImportError.

Without :func:`handling` (the library used from Python) nothing is installed: Ctrl-C is
Python's own KeyboardInterrupt and :func:`check` does nothing.
"""

from __future__ import annotations

import signal
import sys
import threading
from contextlib import contextmanager

__all__ = [
    "Interrupted",
    "handling",
    "deferred",
    "importing",
    "check",
    "note",
    "pending",
    "exit_status",
    "signal_of",
    "signal_text",
    "install_for_startup",
]

SIGNALS = (signal.SIGINT, signal.SIGTERM)

# signum: the first signal received; deferring: one entry per open deferred block (its
# ``insist``), innermost last.
_state = {"signum": None, "deferring": [], "installed": False, "previous": {}, "startup": False}


class Interrupted(KeyboardInterrupt):
    """The command was stopped by a signal (``signum``: SIGINT for Ctrl-C, SIGTERM)."""

    def __init__(self, signum: int):
        super().__init__(signal_text(signum))
        self.signum = int(signum)


def signal_text(signum: int) -> str:
    """'SIGINT (Ctrl-C)' or 'SIGTERM' (or the signal's name)."""
    try:
        name = signal.Signals(signum).name
    except ValueError:
        name = f"signal {signum}"
    return f"{name} (Ctrl-C)" if signum == signal.SIGINT else name


def signal_of(exc: BaseException | None = None) -> int:
    """The signal that stopped the command: the recorded one, else that of ``exc`` (an
    :class:`Interrupted`, or a KeyboardInterrupt raised by another handler as 'signal N'),
    else SIGINT (a plain KeyboardInterrupt is Ctrl-C)."""
    if _state["signum"] is not None:
        return _state["signum"]
    if isinstance(exc, Interrupted):
        return exc.signum
    if isinstance(exc, KeyboardInterrupt) and exc.args:
        words = str(exc.args[0]).split()
        if len(words) == 2 and words[0] == "signal" and words[1].isdigit():
            return int(words[1])
    return int(signal.SIGINT)


def exit_status(exc: BaseException | None = None) -> int:
    """128 + the signal (130 for Ctrl-C, 143 for SIGTERM)."""
    return 128 + signal_of(exc)


def pending() -> int | None:
    """The signal received since :func:`handling` began, if any."""
    return _state["signum"]


def note(signum: int) -> None:
    """Records ``signum`` as the signal that stops the command, when another handler (the
    hardware session's) caught it instead of ours; does nothing outside :func:`handling`."""
    if _state["installed"] and _state["signum"] is None:
        _state["signum"] = int(signum)


def check() -> None:
    """Raises :class:`Interrupted` if a signal was received (even if its exception was
    swallowed on the way); does nothing otherwise or outside :func:`handling`."""
    if _state["signum"] is not None and not _state["deferring"]:
        raise Interrupted(_state["signum"])


def _handler(signum, frame):
    first = _state["signum"] is None
    if first:
        _state["signum"] = signum
    deferring = _state["deferring"]
    if deferring and (first or not deferring[-1]):
        return  # recorded; raised when the deferred block ends
    raise Interrupted(_state["signum"])


def _install() -> None:
    if _state["installed"] or threading.current_thread() is not threading.main_thread():
        return
    for sig in SIGNALS:
        _state["previous"][sig] = signal.signal(sig, _handler)
    _state["installed"] = True


def _uninstall() -> None:
    if not _state["installed"]:
        return
    for sig, previous in _state["previous"].items():
        signal.signal(sig, previous if previous is not None else signal.SIG_DFL)
    _state["previous"].clear()
    _state["installed"] = False


class _ImportCheckpoint:
    """A ``sys.meta_path`` entry that finds nothing: it raises a signal received during
    :func:`importing` at every following import statement (libraries that guard optional
    imports with ``except BaseException`` swallow one; the next import raises again)."""

    def find_spec(self, name, path=None, target=None):
        if _state["signum"] is not None:
            raise Interrupted(_state["signum"])
        return None


_CHECKPOINT = _ImportCheckpoint()


def _checkpoint_imports(on: bool) -> None:
    if on and _CHECKPOINT not in sys.meta_path:
        sys.meta_path.insert(0, _CHECKPOINT)
    elif not on and _CHECKPOINT in sys.meta_path:
        sys.meta_path.remove(_CHECKPOINT)


@contextmanager
def importing():
    """For a block of slow imports: a signal is recorded and raised at the next import
    statement (or, if that is swallowed, when the block ends)."""
    _state["deferring"].append(False)
    _checkpoint_imports(True)
    try:
        yield
    finally:
        _checkpoint_imports(False)
        _state["deferring"].pop()
    check()


def install_for_startup() -> None:
    """Installs the handlers as the program's first act (before its slow imports), in
    deferred mode: a signal before ``main`` runs is recorded and raised by its first
    checkpoint. For the ``drake-rus`` program only (until ``main`` ends)."""
    if _state["startup"]:
        return
    _install()
    _state["deferring"].append(False)
    _state["startup"] = True


@contextmanager
def handling():
    """Installs the SIGINT / SIGTERM handlers for the block (main thread only) and restores
    the previous ones afterwards. A signal received before, during start-up, counts."""
    startup = _state["startup"]
    _state["startup"] = False
    if startup:  # install_for_startup's deferral ends here
        _state["deferring"].clear()
    else:
        _state["signum"] = None
    installed_here = not _state["installed"]
    _install()
    try:
        yield
    finally:
        # Python's own handlers again: after the command, a signal acts as it always does
        # (a hang while the interpreter shuts down stays interruptible).
        _state["deferring"].clear()
        _state["signum"] = None
        if installed_here or startup:
            _uninstall()


@contextmanager
def deferred(reraise: bool = True, insist: bool = False):
    """Holds signals back for the block: they are recorded, and with ``reraise`` raised as
    :class:`Interrupted` when the block ends (also one received before it). ``insist``: a
    second signal during the block is raised at once (the user insists)."""
    _state["deferring"].append(bool(insist))
    try:
        yield
    finally:
        _state["deferring"].pop()
    if reraise:
        check()
