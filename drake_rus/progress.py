"""Running a simulation with a progress bar and an optional Meshcat recording."""

from pathlib import Path

from tqdm import tqdm

from drake_rus.io_utils import write_text_atomic


def AdvanceWithProgress(simulator, t_final: float, desc: str = "simulating",
                        step: float = 0.1, disable: bool | None = None, on_step=None,
                        should_stop=None) -> None:
    """Advances ``simulator`` to ``t_final`` (s) in ``step`` chunks with a tqdm bar.

    ``on_step(context)`` is called after each chunk (e.g. to update a phase label);
    ``should_stop(context)`` ends the run early when it returns True. The bar is hidden when
    stderr is not a terminal unless ``disable=False``.
    """
    context = simulator.get_context()
    t0 = context.get_time()
    with tqdm(total=round(t_final - t0, 3), desc=desc, unit="sim s", disable=disable,
              bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} sim s [{elapsed}<{remaining}]"
              ) as bar:
        while context.get_time() < t_final - 1e-12:
            t_next = min(t_final, context.get_time() + step)
            simulator.AdvanceTo(t_next)
            bar.update(round(t_next - bar.n - t0, 6))
            if on_step is not None:
                postfix = on_step(context)
                if postfix:
                    bar.set_postfix_str(postfix)
            if should_stop is not None and should_stop(context):
                break


def SaveMeshcatRecording(meshcat, path: str | Path) -> Path:
    """Stops the recording, publishes it and writes a standalone HTML file (atomically)."""
    meshcat.StopRecording()
    meshcat.PublishRecording()
    return write_text_atomic(path, meshcat.StaticHtml())
