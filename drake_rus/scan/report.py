"""What a scan leaves on disk for a person to look at.

``summary.json``; ``partial_cloud.ply`` and ``registered_template.ply`` (base frame, m);
``registration.png`` (partial cloud on the registered and the true template, like the seed's
Fig. 7/8); ``coverage.png`` (V against frames and against eps, like Fig. 10, and the probe
path); ``traces.png`` (contact force, approach-vector tilt, manipulability, phases);
``pivot_frames.png`` (emulated frames of the pivot with the segmentation, like Fig. 11c);
``start_plan.png`` (the start planner's acoustic window, depth preset and rejected windows);
``loop_timing.png`` (a live run: each control tick's compute time and lag, phases).
Every file is written to a temporary name and renamed when complete.
"""

import json
from pathlib import Path

import matplotlib
import numpy as np
import trimesh

from drake_rus.anatomy.tissue_colors import mask_handles, mask_overlay
from drake_rus.control.supervisor import Phase
from drake_rus.io_utils import atomic_path, save_figure, write_text_atomic
from drake_rus.scan.planning import plot_start_plan

# Background of each phase in traces.png; every phase has a colour of its own (a white
# swatch would be blank in the legend).
PHASE_COLORS = {
    "APPROACH": "#dddddd",
    "EXPLORE": "#cfe8ff",
    "LOCALIZE": "#ffe9b3",
    "TRANSIT": "#e6d5ff",
    "PIVOT": "#d4f5d4",
    "DONE": "#8fd18f",
    "ABORT": "#ffc9c9",
}


def _plt():
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path):
    save_figure(fig, path, dpi=110)


def write_ply(path: Path, points: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        trimesh.PointCloud(np.asarray(points, float)).export(tmp, file_type="ply")


def plot_registration(result, path: Path) -> None:
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(12, 4.2))
    views = [
        (0, 1, "x (mm)", "y (mm)", "top view (x-y)"),
        (1, 2, "y (mm)", "z (mm)", "side view (y-z)"),
        (0, 2, "x (mm)", "z (mm)", "front view (x-z)"),
    ]
    true_shape = result.truth.kidney_points_B if result.truth is not None else np.zeros((0, 3))
    for ax, (i, j, xl, yl, title) in zip(axes, views):
        if len(true_shape):
            sub = true_shape[:: max(1, len(true_shape) // 3000)]
            ax.scatter(sub[:, i] * 1e3, sub[:, j] * 1e3, s=1, c="#bbbbbb", label="true kidney")
        if result.registered_template_B is not None:
            t = result.registered_template_B
            ax.scatter(
                t[:, i] * 1e3,
                t[:, j] * 1e3,
                s=1,
                c="tab:red",
                alpha=0.5,
                label="registered template",
            )
        c = result.partial_cloud_B
        if len(c):
            c = c[:: max(1, len(c) // 3000)]
            ax.scatter(c[:, i] * 1e3, c[:, j] * 1e3, s=1.5, c="k", label="explored cloud")
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        ax.set_title(title)
        ax.set_aspect("equal", adjustable="datalim")
    axes[0].legend(loc="best", fontsize=7, markerscale=5)
    fig.suptitle(f"Registration: {result.patient}")
    fig.tight_layout()
    _save(fig, path)


def plot_coverage(result, metrics: dict, path: Path) -> None:
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    # Pole to pole (the paper's eps, n, V) and the whole pivot (both legs) beside it.
    for key_V, key_eps, label, style in (
        ("V_whole_pivot_curve", "eps_whole_pivot_curve_mm", "whole pivot (both legs)", ":"),
        ("V_curve", "eps_curve_mm", "pole to pole (paper)", "-"),
    ):
        V = np.asarray(metrics.get(key_V) or [])
        eps = np.asarray(metrics.get(key_eps) or [])
        if len(V):
            axes[0].plot(np.arange(1, len(V) + 1), V, style, color="tab:green", label=label)
            axes[1].plot(eps[: len(V)], V, style, color="tab:green", label=label)
    axes[0].set_xlabel("frames during the pivot, n")
    axes[0].set_ylabel("volume reconstruction ratio V")
    axes[0].set_ylim(0, 1.05)
    axes[0].grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    axes[1].set_xlabel(r"imaging-window path length $\varepsilon$ (mm)")
    axes[1].set_ylabel("V")
    axes[1].set_ylim(0, 1.05)
    axes[1].grid(alpha=0.3)
    p = (
        np.array([f.X_BP.translation() for f in result.frames])
        if result.frames
        else np.zeros((0, 3))
    )
    phases = np.array([f.phase for f in result.frames])
    for phase in Phase:
        sel = phases == int(phase)
        if sel.any():
            axes[2].plot(p[sel, 0] * 1e3, p[sel, 1] * 1e3, ".", ms=3, label=phase.name)
    axes[2].set_xlabel("tip x (mm)")
    axes[2].set_ylabel("tip y (mm)")
    axes[2].set_title("probe tip path (base frame)")
    axes[2].set_aspect("equal", adjustable="datalim")
    axes[2].legend(fontsize=7)
    V_text = "unknown" if metrics["volume_ratio"] is None else f"{metrics['volume_ratio']:.3f}"
    whole = (
        f"; whole pivot n = {metrics['n_whole_pivot']}, eps = "
        f"{metrics['eps_whole_pivot_mm']:.1f} mm"
        if "n_whole_pivot" in metrics
        else ""
    )
    fig.suptitle(
        f"Coverage pole to pole (paper): V = {V_text}, n = {metrics['n_frames']} "
        f"frames, eps = {metrics['eps_mm']:.1f} mm{whole}",
        fontsize=9,
    )
    fig.tight_layout()
    _save(fig, path)


def _shade_phases(ax, phases):
    for name, a, b in phases:
        ax.axvspan(a, b, color=PHASE_COLORS.get(name, "#ffffff"), alpha=0.6, lw=0)


def plot_traces(result, path: Path) -> None:
    plt = _plt()
    fig, axes = plt.subplots(3, 1, figsize=(10, 7.5), sharex=True)
    t, F = result.logs["force"][0], result.logs["force"][1][0]
    _shade_phases(axes[0], result.phases)
    if "force_true" in result.logs:  # simulation truth
        tt, Ft = result.logs["force_true"][0], -result.logs["force_true"][1][5]
        axes[0].plot(tt, Ft, color="tab:gray", lw=1.5, label="true contact force")
    axes[0].plot(t, F, color="tab:blue", lw=1, label="estimated, filtered")
    axes[0].axhline(
        result.scenario.controller.desired_force, ls=":", color="tab:red", label="desired"
    )
    axes[0].axhline(
        result.scenario.safety.force_ceiling, ls="--", color="darkred", lw=0.8, label="ceiling"
    )
    axes[0].set_ylabel("F_z (N)")
    axes[0].legend(fontsize=7, loc="upper right")
    ta, a = result.logs["a_des"][0], result.logs["a_des"][1]
    tilt = np.degrees(np.arccos(np.clip(-a[2], -1, 1)))
    frames_t = [f.time for f in result.frames]
    actual = [
        np.degrees(np.arccos(np.clip(-f.X_BP.rotation().matrix()[2, 2], -1, 1)))
        for f in result.frames
    ]
    _shade_phases(axes[1], result.phases)
    axes[1].plot(ta, tilt, color="tab:orange", label="desired tilt of a from vertical")
    axes[1].plot(frames_t, actual, ".", ms=2, color="k", label="actual")
    axes[1].set_ylabel("tilt (deg)")
    axes[1].legend(fontsize=7, loc="upper left")
    tm, m = result.logs["manipulability"][0], result.logs["manipulability"][1][0]
    _shade_phases(axes[2], result.phases)
    axes[2].plot(tm, m, color="tab:purple")
    axes[2].set_ylabel("manipulability")
    axes[2].set_xlabel("time (s)")
    handles = [
        plt.Rectangle((0, 0), 1, 1, facecolor=c, edgecolor="0.5", lw=0.5, alpha=0.6)
        for c in PHASE_COLORS.values()
    ]
    fig.legend(handles, PHASE_COLORS.keys(), loc="lower center", ncol=7, fontsize=7)
    fig.suptitle(f"Scan traces: {result.patient} ({result.status})")
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    _save(fig, path)


def plot_frames(result, path: Path, count: int = 6) -> None:
    if not result.images:
        return
    plt = _plt()
    picks = np.linspace(0, len(result.images) - 1, min(count, len(result.images))).astype(int)
    fig, axes = plt.subplots(1, len(picks), figsize=(2.6 * len(picks), 2.9))
    axes = np.atleast_1d(axes)
    for ax, k in zip(axes, picks):
        t, grey, mask = result.images[k]
        ax.imshow(mask_overlay(grey, mask))
        ax.set_title(f"t = {t:.1f} s", fontsize=8)
        ax.axis("off")
    fig.suptitle("Emulated frames during the pivot")
    fig.legend(handles=mask_handles(), loc="lower center", fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    _save(fig, path)


def plot_loop_timing(result, path: Path) -> None:
    """Each tick's compute time and lag (ms) of a live run over the scan's time, with the
    tick and ``safety.realtime_lag`` marked; nothing without a loop trace."""
    trace = getattr(result, "loop_trace", None)
    timing = getattr(result, "loop_timing", None)
    if not trace or timing is None or len(trace["t"]) == 0:
        return
    plt = _plt()
    fig, axes = plt.subplots(2, 1, figsize=(10, 5.5), sharex=True)
    t = trace["t"]
    tick_ms = timing["tick_ms"]
    for ax, key, label in (
        (axes[0], "compute", "compute per tick (ms)"),
        (axes[1], "lag", "lag at the tick's start (ms)"),
    ):
        _shade_phases(ax, result.phases)
        values = 1e3 * np.asarray(trace[key][: len(t)], float)
        ax.plot(t[: len(values)], values, ".", ms=1.5, color="k")
        ax.axhline(tick_ms, ls=":", color="tab:blue", lw=1, label=f"tick {tick_ms:g} ms")
        ax.set_yscale("symlog", linthresh=1.0)
        ax.set_ylabel(label)
        s = timing[f"{key}_ms"]
        ax.set_title(
            f"p50 {s['p50']:.2f}, p99 {s['p99']:.2f}, p99.9 {s['p999']:.2f}, max {s['max']:.2f} ms",
            fontsize=8,
        )
    axes[1].axhline(
        1e3 * result.scenario.safety.realtime_lag,
        ls="--",
        color="darkred",
        lw=0.8,
        label="safety.realtime_lag",
    )
    axes[0].legend(fontsize=7, loc="upper right")
    axes[1].legend(fontsize=7, loc="upper right")
    axes[1].set_xlabel("scan time (s)")
    load = timing.get("load_average") or {}
    fig.suptitle(
        f"Control loop timing: {result.patient} ({result.status}); {timing['ticks']} ticks, "
        f"{timing['slips']} slips; load average {load.get('1min', float('nan')):.1f} on "
        f"{load.get('cpus')} CPUs"
    )
    fig.tight_layout()
    _save(fig, path)


def WriteScanOutputs(result, metrics: dict, summary: dict, out: Path) -> list[Path]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    write_text_atomic(out / "summary.json", json.dumps(summary, indent=2, default=str) + "\n")
    written.append(out / "summary.json")
    if len(result.partial_cloud_B):
        write_ply(out / "partial_cloud.ply", result.partial_cloud_B)
        written.append(out / "partial_cloud.ply")
    if result.registered_template_B is not None:
        write_ply(out / "registered_template.ply", result.registered_template_B)
        written.append(out / "registered_template.ply")
    if result.start_plan is not None:
        plot_start_plan(
            result.start_plan,
            result.scenario.imaging,
            out / "start_plan.png",
            title=f"Start planner: {result.patient}",
        )
        written.append(out / "start_plan.png")
    for name, fn in (
        ("registration.png", lambda p: plot_registration(result, p)),
        ("coverage.png", lambda p: plot_coverage(result, metrics, p)),
        ("traces.png", lambda p: plot_traces(result, p)),
        ("pivot_frames.png", lambda p: plot_frames(result, p)),
        ("loop_timing.png", lambda p: plot_loop_timing(result, p)),
    ):
        fn(out / name)
        if (out / name).exists():
            written.append(out / name)
    return written
