"""Study runs in kinematic mode (the default, fast twin: :mod:`drake_rus.experiments.kinematic`,
probe poses planned exactly, no robot dynamics); deterministic given their task (seeded
starts).

- :func:`run_kinematic_task`: one run of any study (er-sweep, starts, efficiency,
  template): exploration (ER 0: the initial alignment alone, III-C), registration, E_trans
  and E_rot,x, and for the efficiency study every strategy's sweep
  (:func:`efficiency_of`).
- :func:`exploration`: a run's exploration; runs that differ only in ER share one per
  process.
- :func:`sweep_entry`: the sweep costs of one sweep (:mod:`drake_rus.metrics.sweep`, the
  same functions the closed-loop scan uses): V against n and eps pole to pole (the
  paper's), the whole pivot's n, eps and V beside them, n and eps needed to reach
  V = 0.9, the pivot legs the tilt cap ended.
- :func:`efficiency_of`: per strategy (III-E, Fig. 10: OP, GT-OP, NOP, SL, and OP-PE beyond
  the paper) its sweep costs and the kidney volume reconstructed from the sweep's masks
  (:mod:`drake_rus.metrics.reconstruction`), optionally written as NRRD.
"""

from __future__ import annotations

import dataclasses
import math
import re
import time
from pathlib import Path

import numpy as np

from drake_rus.experiments import kinematic as km
from drake_rus.experiments.analysis import STRATEGY_ORDER
from drake_rus.experiments.keys import run_id
from drake_rus.experiments.patients import (
    exploration_travel,
    kidney_length,
    start_visibility,
    task_scenario_and_patient,
    visible_random_start,
)
from drake_rus.experiments.specs import POSE_FROM, STRATEGY_TEXT, StudyTask, check_strategies
from drake_rus.experiments.templates import task_template, template_record
from drake_rus.metrics.core import CoverageAccumulator, e_rot_x, e_trans
from drake_rus.metrics.reconstruction import compound, reconstruct_kidney, write_nrrd
from drake_rus.metrics.sweep import sweep_efficiency

# Coverage at which the sweep costs are also compared (matched coverage).
V_TARGETS = (0.9,)
# The strategies whose reconstructions an efficiency run writes as NRRD (with export_dir).
EXPORT_STRATEGIES = ("OP", "GT-OP")

_EXPLORATIONS: dict = {}


def exploration(task: StudyTask, kp, imager, controller, start_fraction: float, x_offset: float):
    """The exploration of ``task``. Runs that differ only in ER share one full (ER 100%)
    exploration per process and take its prefix (identical to exploring less: see
    ``Sweep.prefix``). ``imager`` is left as the full exploration leaves it (its frame
    counter, which the emulator's speckle of later sweeps depends on, past the full
    exploration's frames) whether or not this process explored before, so a run's numbers
    do not depend on which runs its process ran first (the worker count)."""
    key = (
        task.patient,
        task.posture,
        task.voxel,
        task.segmenter,
        task.seed,
        task.scenario,
        task.scenarios_file,
        task.overrides,
        start_fraction,
        x_offset,
    )
    full = _EXPLORATIONS.get(key)
    if full is not None:
        imager.frame_index += len(full.frames)  # as exploring it here would have
    else:
        full = km.explore(
            kp,
            imager,
            controller,
            exploration_ratio=1.0,
            start_fraction=start_fraction,
            x_offset=x_offset,
            travel=max(kidney_length(kp), controller.kidney_length),
        )
        if len(_EXPLORATIONS) >= 16:
            _EXPLORATIONS.pop(next(iter(_EXPLORATIONS)))
        _EXPLORATIONS[key] = full
    return full.prefix(
        exploration_travel(task.er, task.er_unit, kidney_length(kp), controller.kidney_length)
    )


def _reach(r):
    return None if r is None else {"n": int(r["n"]), "eps_mm": r["eps"] * 1e3}


def sweep_entry(kp, sweep, geometry, controller) -> dict:
    """The sweep costs of one kinematic sweep (:func:`drake_rus.metrics.sweep_efficiency`,
    the definitions the closed-loop scan uses): pole to pole (``n``, ``eps_mm``, ``V``, the
    paper's), the whole pivot (``n_whole_pivot``, ``eps_whole_pivot_mm``,
    ``V_whole_pivot``), n and eps to reach V (``at_V``, pole to pole; ``at_V_whole_pivot``),
    and the pivot legs ended by the tilt cap (``tilt_cap_legs``). Also returns the
    pole-to-pole curves (``curve_eps_mm``, ``curve_V``) and the sweep's events."""

    def coverage():
        return CoverageAccumulator(
            kp.kidney_points_B, kp.voxel_volume, geometry.in_fan, geometry.elevation_width
        )

    eff = sweep_efficiency(
        sweep.poses,
        sweep.visible,
        geometry.depth,
        legs=sweep.leg,
        coverage=coverage,
        V_targets=V_TARGETS,
        angles=sweep.angles,
        max_tilt=controller.max_pivot_tilt if sweep.angles is not None else None,
    )
    return {
        "n": int(eff["n"]),
        "eps_mm": eff["eps"] * 1e3,
        "V": eff["V"],
        "n_whole_pivot": int(eff["n_whole_pivot"]),
        "eps_whole_pivot_mm": eff["eps_whole_pivot"] * 1e3,
        "V_whole_pivot": eff["V_whole_pivot"],
        "at_V": {f"{t:g}": _reach(eff["at_V"][t]) for t in V_TARGETS},
        "at_V_whole_pivot": {f"{t:g}": _reach(eff["at_V_whole_pivot"][t]) for t in V_TARGETS},
        "tilt_cap_legs": list(eff["tilt_cap_legs"]),
        "events": list(sweep.events),
        "curve_eps_mm": np.round(eff["eps_curve"] * 1e3, 3).tolist(),
        "curve_V": np.round(eff["V_curve"], 5).tolist(),
        "pole_to_pole": [int(i) for i in eff["pole_to_pole"][[0, -1]]]
        if len(eff["pole_to_pole"])
        else [],
    }


def run_kinematic_task(task: StudyTask) -> dict:
    """One study run in kinematic mode (the twin)."""
    t0 = time.perf_counter()
    scenario, kp = task_scenario_and_patient(task)
    controller = scenario.controller
    imager = km.Imager(
        kp,
        km.imaging_for(kp, scenario.imaging, scenario.start),
        task.segmenter,
        seed=int(task.seed),
    )
    start_fraction, x_offset, rejected = 0.0, 0.0, None
    if task.study == "starts":
        # Where the kidney is visible (II-A (i)): the same starts as the closed loop's.
        start_fraction, x_offset, rejected = visible_random_start(
            task, kp, controller, start_visibility(kp, imager)
        )
    sweep = exploration(task, kp, imager, controller, start_fraction, x_offset)
    P = sweep.point_cloud()
    template = task_template(task, scenario)
    config = dataclasses.replace(scenario.localization, method=task.method)
    # ER 0: the initial alignment alone, whatever the start frame shows (III-C).
    loc = km.localize_cloud(
        kp,
        P,
        template,
        config,
        sweep.frames[0].X_BP.translation()[:2],
        min_points=50 if float(task.er) > 0 else math.inf,
    )
    result = {
        "run_id": run_id(task),
        "task": task.to_dict(),
        "mode": km.MODE,
        "patient": task.patient,
        "er": task.er,
        "start": task.start,
        "start_fraction": start_fraction,
        "x_offset_mm": x_offset * 1e3,
        "explore_frames": len(sweep.frames),
        "explore_travel_mm": float(sweep.travel[-1] * 1e3),
        "kidney_length_mm": kidney_length(kp) * 1e3,
        "er_unit": task.er_unit,
        "points": int(len(P)),
        "e_trans_mm": e_trans(loc.X_BK, kp.X_BK_true) * 1e3,
        "e_rot_x_deg": math.degrees(e_rot_x(loc.X_BK, kp.X_BK_true)),
        "registration_ms": loc.compute_s * 1e3,
        "iterations": None if loc.result is None else int(loc.result.iterations),
        "localization_note": loc.note,
        "true_volume_ml": kp.kidney_volume * 1e6,
    }
    if rejected is not None:
        result["start_rejected_draws"] = rejected
    if task.study == "template":
        result.update(
            template_record(
                task.template_variant, template, kp, scenario.patient.posture, task.patient
            )
        )
    if task.study == "efficiency":
        result["strategies"] = efficiency_of(
            kp,
            imager,
            controller,
            loc.X_BK,
            float(task.recon_spacing),
            export_dir=task.export_dir,
            name=re.sub(r"[^A-Za-z0-9]+", "-", task.patient).strip("-"),
            strategies=check_strategies(task.strategies or STRATEGY_ORDER),
            pivot_model=km.pivot_model_for(template, imager.imaging),
        )
    result["wall_s"] = time.perf_counter() - t0
    return result


def efficiency_of(
    kp,
    imager,
    controller,
    X_BK_est,
    recon_spacing: float,
    *,
    export_dir=None,
    name: str = "patient",
    strategies=STRATEGY_ORDER,
    pivot_model=None,
) -> dict:
    """Per strategy: :func:`sweep_entry` (pole-to-pole curves and totals, the whole pivot's
    totals, matched coverage, tilt cap) and the reconstructed kidney volume (mL) from the
    pole-to-pole masks; OP-PE (the predicted_end pivot, needs ``pivot_model``) also its
    predicted ends and pre-tilt (``pretilt``: target, end, check frames, window path mm).
    With ``export_dir``, the OP and GT-OP reconstructions are written there as NRRD (kidney
    probability, kidney mask and, for the classical/onnx segmenters, the grey volume)."""
    out = {}
    for s in strategies:
        sweep = km.strategy_sweep(
            kp, imager, s, controller, X_BK_est, keep_images=True, pivot_model=pivot_model
        )
        p2p = sweep.pole_to_pole()
        entry = sweep_entry(kp, sweep, imager.geometry, controller)
        entry.update(
            volume_ml=None,
            volume_error_pct=None,
            sweep="line" if s == "SL" else "pivot",
            pivot_pose_from=POSE_FROM[s],
            text=STRATEGY_TEXT[s],
        )
        if sweep.info:
            i = sweep.info
            entry["pretilt"] = {
                "predicted_ends_deg": [math.degrees(x) for x in i["predicted_ends"]],
                "target_deg": math.degrees(i["pretilt_target"]),
                "end_deg": math.degrees(i["pretilt_end"]),
                "check_frames": i["pretilt_check_frames"],
                "eps_mm": i["eps_pretilt"] * 1e3,
            }
        if p2p.frames:
            try:
                rec = reconstruct_kidney(
                    [f.mask for f in p2p.frames], p2p.poses, imager.geometry, spacing=recon_spacing
                )
                entry["volume_ml"] = rec["volume_ml"]
                entry["volume_error_pct"] = 100 * (rec["volume_ml"] / (kp.kidney_volume * 1e6) - 1)
                if export_dir is not None and s in EXPORT_STRATEGIES:
                    d = Path(export_dir)
                    tag = f"{name}__{s}"
                    note = (
                        f"drake-rus {s} sweep of {name}, kinematic mode; axes = robot base "
                        "frame x, y, z (mm)"
                    )
                    write_nrrd(
                        d / f"{tag}__kidney_probability.nrrd",
                        rec["reconstruction"].values,
                        rec["grid"],
                        description=note,
                    )
                    write_nrrd(
                        d / f"{tag}__kidney_mask.nrrd", rec["mask"], rec["grid"], description=note
                    )
                    if all(f.image is not None for f in p2p.frames):
                        grey = compound(
                            [f.image for f in p2p.frames], p2p.poses, imager.geometry, rec["grid"]
                        )
                        write_nrrd(
                            d / f"{tag}__grey.nrrd", grey.values, rec["grid"], description=note
                        )
                    entry["nrrd"] = sorted(str(p.name) for p in d.glob(f"{tag}__*.nrrd"))
            except ValueError as e:
                entry["volume_note"] = str(e)
        out[s] = entry
    return out
