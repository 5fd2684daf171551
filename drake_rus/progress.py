"""Running a simulation with a progress bar and an optional Meshcat recording.

The bar tells the truth: it counts simulated time towards the run's *expected* length (not
a time cap), shows the current phase, and when stderr is not a terminal (a log file, CI) it
is replaced by one line per phase and, in a long run, a line every ``PROGRESS_LINE_S`` s of
wall time. A signal (Ctrl-C, SIGTERM) ends the run after the current chunk at the latest
(``drake_rus.interrupts.check``).
"""

import sys
import time
from pathlib import Path

from tqdm import tqdm

from drake_rus import interrupts
from drake_rus.io_utils import write_text_atomic

# Without a terminal, a progress line at least this often (s of wall time) in a long run.
PROGRESS_LINE_S = 30.0


def stderr_is_terminal() -> bool:
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


def AdvanceWithProgress(
    simulator,
    t_final: float,
    desc: str = "simulating",
    step: float = 0.1,
    disable: bool | None = None,
    on_step=None,
    should_stop=None,
    expected: float | None = None,
    log_phases: bool | None = None,
    advance=None,
) -> None:
    """Advances ``simulator`` to ``t_final`` (s, a cap) in ``step`` chunks with a tqdm bar.

    ``on_step(context)`` is called after each chunk and returns a label (e.g. the phase),
    shown after the bar; ``should_stop(context)`` ends the run early when it returns True.
    ``expected`` (s): the run's expected simulated length, the bar's total (default
    ``t_final``); a run that goes on longer stretches the total, a run that stops early
    ends the bar at 100 %. The bar is hidden when stderr is not a terminal unless
    ``disable=False``; then (``log_phases`` None) one line per new label goes to stderr
    instead, unless ``disable=True``. ``advance(t)`` advances the simulator to t (default
    ``simulator.AdvanceTo``; a live run paces it, ``drake_rus.pacing``).
    """
    context = simulator.get_context()
    t0 = context.get_time()
    span = t_final - t0
    total = span if expected is None else max(min(expected, span), step)
    terminal = stderr_is_terminal()
    if log_phases is None:
        log_phases = disable is None and not terminal
    start = time.perf_counter()
    last = [None]
    said = [start]  # when the last line was printed (wall clock)

    def log(label):
        now = time.perf_counter()
        if log_phases and label and label != last[0]:
            print(
                f"{desc}: {label} at {context.get_time() - t0:.1f} sim s "
                f"({now - start:.0f} s wall)",
                file=sys.stderr,
                flush=True,
            )
            said[0] = now
        elif log_phases and now - said[0] >= PROGRESS_LINE_S:
            print(
                f"{desc}: {context.get_time() - t0:.1f} of {span:.1f} sim s"
                f"{' in ' + label if label else ''} ({now - start:.0f} s wall)",
                file=sys.stderr,
                flush=True,
            )
            said[0] = now
        last[0] = label

    with tqdm(
        total=round(total, 3),
        desc=desc,
        unit="sim s",
        disable=(not terminal) if disable is None else disable,
        bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} sim s [{elapsed}<{remaining}]{postfix}",
    ) as bar:
        if on_step is not None:
            label = on_step(context)
            log(label)
            if label:
                bar.set_postfix_str(label, refresh=False)
        while context.get_time() < t_final - 1e-12:
            t_next = min(t_final, context.get_time() + step)
            (advance or simulator.AdvanceTo)(t_next)
            done = context.get_time() - t0
            if done > 0.95 * bar.total:  # longer than expected: stretch, never > 100 %
                bar.total = round(min(span, max(done / 0.95, done + step)), 3)
            bar.update(round(done - bar.n, 6))
            interrupts.check()  # a signal whose exception was swallowed on the way
            label = None if on_step is None else on_step(context)
            log(label)
            if label:
                bar.set_postfix_str(label, refresh=False)
            if should_stop is not None and should_stop(context):
                break
        bar.total = round(max(context.get_time() - t0, 1e-3), 3)  # the run ends at 100 %
        bar.n = bar.total
        bar.refresh()


def SaveMeshcatRecording(meshcat, path: str | Path) -> Path:
    """Stops the recording, publishes it and writes a standalone HTML file (atomically)."""
    meshcat.StopRecording()
    meshcat.PublishRecording()
    return write_text_atomic(path, meshcat.StaticHtml())
