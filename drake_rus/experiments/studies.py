"""The seed's section III studies on the virtual cohort, in kinematic mode, run by run.

Studies (each a list of independent runs; a run is a plain dict, its result a JSON file):

- ``er-sweep`` (III-C, Fig. 7d): exploration ratios 0..100% in 10% steps per patient;
  paired t-tests (``scipy.stats.ttest_rel``) of E_trans and E_rot,x at each ER against ER
  100%. Critical ER = the smallest ER from which on every ER is not significantly different
  from 100% (p > 0.05) in both errors (the seed: "the smallest ER at which both errors are
  not significantly different"; requiring it for the larger ERs too guards against a lucky
  low ER).
- ``starts`` (III-D, Fig. 9d): at the critical ER, five random starts per patient inside the
  E-ROI (start fraction along y leaving room for the whole ER x L_m of travel, and an x
  offset within the middle half of the E-ROI's width), pairwise paired t-tests of the
  starts over patients with Bonferroni correction (10 pairs: p < 0.005).
- ``efficiency`` (III-E, Fig. 10): OP (at T* of the registered pose), GT-OP, NOP and SL per
  patient: V against n and eps (pole to pole), totals, paired t-tests OP vs the others
  (Bonferroni over the comparisons), and the kidney volume reconstructed from each sweep's
  masks (:mod:`drake_rus.metrics.reconstruction`) against the true volume.

Every run is kinematic (:mod:`drake_rus.experiments.kinematic`): probe poses planned
exactly, no robot dynamics. Runs are deterministic given their dict (seeded starts).
:func:`run_study` executes runs through Dask (:func:`run_tasks`), writing each result as
it finishes, so an interrupted study resumes.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import re
import time
import zlib
from pathlib import Path

import numpy as np

from drake_rus.io_utils import write_text_atomic

ER_GRID = tuple(round(0.1 * k, 1) for k in range(11))
STRATEGY_ORDER = ("OP", "GT-OP", "NOP", "SL")
PAPER = {
    "er_sweep": {"critical_er": 0.6, "p_e_trans_at_60": 0.0744, "p_e_rot_at_60": 0.3523,
                 "e_trans_mm_at_60": (10.81, 7.08), "e_rot_x_deg_at_60": (11.58, 7.61)},
    "localization": {"e_trans_mm": (8.73, 6.93), "e_rot_x_deg": (12.86, 20.86)},
    "starts": "no significant difference between the five starts (10 paired t-tests, "
              "Bonferroni p > 0.005) in either error",
    "efficiency": {"eps_reduction_vs_SL_mm": (1.71, 29.62),
                   "eps_reduction_vs_NOP_mm": (24.66, 21.50),
                   "eps_extra_vs_GT_OP_mm": (11.71, 12.60)},
    "volume_loa": "+-18% limits of agreement, freehand 3-D US vs MRI (Bakker 1999)",
}


# ------------------------------------------------------------------------------- patients
def expand_patients(text: str) -> list[str]:
    """Patient specs from a comma list of ``test:0-14``, ``seed:100-120``, ``train:3`` or
    patient paths. Ranges are inclusive."""
    specs = []
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        m = re.fullmatch(r"(test|train|seed):(\d+)-(\d+)", part)
        if m:
            lo, hi = int(m.group(2)), int(m.group(3))
            if hi < lo:
                raise ValueError(f"--patients: range {part!r} runs backwards")
            specs += [f"{m.group(1)}:{k}" for k in range(lo, hi + 1)]
        elif re.fullmatch(r"(test|train|seed):\d+", part) or "/" in part or "." in part:
            specs.append(part)
        else:
            raise ValueError(f"--patients: cannot read {part!r} (expected test:0-14, "
                             "seed:100-120, train:3 or a patient path)")
    if not specs:
        raise ValueError("--patients: no patients given")
    return specs


# ------------------------------------------------------------------------------- run specs
@dataclasses.dataclass(frozen=True)
class StudyOptions:
    """What every run of a study shares."""
    scenario: str = "default"
    scenarios_file: str | None = None
    overrides: str | None = None
    segmenter: str = "oracle"
    method: str = "seed"            # localization method of the runs (the seed's by default)
    voxel: float = 0.002            # label-volume voxel size (m)
    seed: int = 0                   # random starts, emulator speckle
    recon_spacing: float = 0.001    # reconstruction grid (m)

    def base(self) -> dict:
        return dataclasses.asdict(self)


def run_id(task: dict) -> str:
    """File-name-safe unique name of a run."""
    patient = re.sub(r"[^A-Za-z0-9]+", "-", str(task["patient"])).strip("-")
    parts = [task["study"], patient, f"er{int(round(task['er'] * 100)):03d}"]
    if task["study"] == "closed-loop":
        parts.append(f"f{int(round(task['start_fraction'] * 100)):03d}")
    if task["study"] == "starts":
        parts.append(f"s{task['start']}")
    return "__".join(parts)


def er_sweep_tasks(patients, options: StudyOptions, ers=ER_GRID) -> list[dict]:
    return [dict(options.base(), study="er-sweep", patient=p, er=float(er), start=-1)
            for p in patients for er in ers]


def starts_tasks(patients, options: StudyOptions, er: float, n_starts: int = 5) -> list[dict]:
    return [dict(options.base(), study="starts", patient=p, er=float(er), start=k)
            for p in patients for k in range(n_starts)]


def efficiency_tasks(patients, options: StudyOptions, er: float,
                     export_dir: str | None = None) -> list[dict]:
    """``export_dir``: write the OP and GT-OP reconstructions there as NRRD."""
    return [dict(options.base(), study="efficiency", patient=p, er=float(er), start=-1,
                 export_dir=None if export_dir is None else str(export_dir))
            for p in patients]


# ------------------------------------------------------------------------------- one run
@functools.lru_cache(maxsize=4)
def _scenario(name, filename, overrides):
    from drake_rus.scenario import DEFAULT_SCENARIOS_FILE, LoadScenario
    return LoadScenario(filename=filename or DEFAULT_SCENARIOS_FILE, scenario_name=name,
                        scenario_text=overrides)


@functools.lru_cache(maxsize=2)
def _template(path):
    from drake_rus.localization.localize import load_registration_template
    return load_registration_template(path)


_PATIENTS: dict = {}


def prepared_patient(spec: str, side: str, posture: str, voxel: float, X_BPt):
    """Kinematic patient, cached per process (label volumes take seconds to build)."""
    from drake_rus.anatomy import load_patient
    from drake_rus.experiments.kinematic import prepare_patient
    key = (spec, side, posture, voxel, tuple(X_BPt.GetAsMatrix4().ravel()))
    if key not in _PATIENTS:
        if len(_PATIENTS) >= 16:
            _PATIENTS.pop(next(iter(_PATIENTS)))
        patient = load_patient(spec, side=side, posture=posture, voxel_size=voxel,
                               progress=False)
        _PATIENTS[key] = prepare_patient(patient, X_BPt)
    return _PATIENTS[key]


def random_start(task: dict, kp, controller) -> tuple[float, float]:
    """(start_fraction, x_offset) of random start ``task['start']`` (deterministic in the
    study seed, the patient and the start index)."""
    rng = np.random.default_rng([int(task["seed"]), zlib.crc32(str(task["patient"]).encode()),
                                 int(task["start"])])
    room = max(0.0, 1.0 - task["er"] * controller.kidney_length / max(kp.roi.length_y, 1e-9))
    width = kp.roi.x_max - kp.roi.x_min
    return float(rng.uniform(0.0, room)), float(rng.uniform(-0.25, 0.25) * width)


_EXPLORATIONS: dict = {}


def exploration(task: dict, kp, imager, controller, start_fraction: float, x_offset: float):
    """The exploration of ``task``. Runs that differ only in ER share one full (ER 100%)
    exploration per process and take its prefix (identical to exploring less: see
    ``Sweep.prefix``)."""
    from drake_rus.experiments import kinematic as km
    key = (task["patient"], task["voxel"], task["segmenter"], task["seed"], task["scenario"],
           task.get("scenarios_file"), task.get("overrides"), start_fraction, x_offset)
    full = _EXPLORATIONS.get(key)
    if full is None:
        full = km.explore(kp, imager, controller, exploration_ratio=1.0,
                          start_fraction=start_fraction, x_offset=x_offset)
        if len(_EXPLORATIONS) >= 16:
            _EXPLORATIONS.pop(next(iter(_EXPLORATIONS)))
        _EXPLORATIONS[key] = full
    return full.prefix(float(task["er"]) * controller.kidney_length)


def closed_loop_tasks(patients, options: StudyOptions, er: float,
                      start_fraction: float = 0.1) -> list[dict]:
    """A few closed-loop dynamic scans (``RunScan``) with their kinematic twins."""
    return [dict(options.base(), study="closed-loop", patient=p, er=float(er), start=-1,
                 start_fraction=float(start_fraction)) for p in patients]


def run_closed_loop(task: dict) -> dict:
    """One closed-loop dynamic scan (the lead's ``RunScan``: MultibodyPlant, controller,
    contact) and the same scan in kinematic mode (same patient, start, ER, segmenter,
    localization method): E_trans, E_rot,x, and n, eps, V over both pivot legs (what
    ``ScanMetrics`` counts)."""
    from drake_rus.experiments import kinematic as km
    from drake_rus.metrics.core import e_rot_x, e_trans
    from drake_rus.scan import RunScan, ScanMetrics

    t0 = time.perf_counter()
    base = _scenario(task["scenario"], task.get("scenarios_file"), task.get("overrides"))
    scenario = dataclasses.replace(
        base, controller=dataclasses.replace(base.controller, exploration_ratio=task["er"]),
        localization=dataclasses.replace(base.localization, method=task["method"]),
        imaging=dataclasses.replace(base.imaging, segmenter=task["segmenter"]))
    X_BPt = scenario.patient.X_BPt.GetDeterministicValue()
    kp = prepared_patient(task["patient"], scenario.patient.side, scenario.patient.posture,
                          float(task["voxel"]), X_BPt)
    template = _template(scenario.localization.template)
    scan = RunScan(scenario, kp.patient, template, progress=False,
                   start_fraction=float(task["start_fraction"]))
    m = ScanMetrics(scan)
    closed = {"status": scan.status, "reason": scan.reason, "e_trans_mm": m["e_trans_mm"],
              "e_rot_x_deg": m["e_rot_x_deg"], "n": m["n_frames"], "eps_mm": m["eps_mm"],
              "V": m["volume_ratio"], "sim_s": scan.sim_s, "wall_s": scan.wall_s,
              "mode": "closed-loop dynamic simulation"}
    t1 = time.perf_counter()
    imager = km.Imager(kp, scenario.imaging, task["segmenter"], seed=int(task["seed"]))
    sweep = km.explore(kp, imager, scenario.controller, exploration_ratio=task["er"],
                       start_fraction=float(task["start_fraction"]))
    loc = km.localize_cloud(kp, sweep.point_cloud(), template, scenario.localization,
                            sweep.frames[0].X_BP.translation()[:2])
    op = km.strategy_sweep(kp, imager, "OP", scenario.controller, loc.X_BK)
    c = km.sweep_curves(kp, op, imager.geometry)
    kin = {"e_trans_mm": e_trans(loc.X_BK, kp.X_BK_true) * 1e3,
           "e_rot_x_deg": math.degrees(e_rot_x(loc.X_BK, kp.X_BK_true)),
           "n": int(c["n_frames"]), "eps_mm": c["eps_total"] * 1e3, "V": c["V_final"],
           "wall_s": time.perf_counter() - t1, "mode": km.MODE}
    return {"run_id": run_id(task), "task": task, "mode": "closed-loop + kinematic twin",
            "patient": task["patient"], "er": task["er"], "start": -1,
            "closed_loop": closed, "kinematic": kin, "wall_s": time.perf_counter() - t0}


def run_task(task: dict) -> dict:
    """Executes one run (kinematic) and returns its JSON-ready result."""
    if task["study"] == "closed-loop":
        return run_closed_loop(task)
    from drake_rus.experiments import kinematic as km
    from drake_rus.metrics.core import e_rot_x, e_trans

    t0 = time.perf_counter()
    scenario = _scenario(task["scenario"], task.get("scenarios_file"), task.get("overrides"))
    X_BPt = scenario.patient.X_BPt.GetDeterministicValue()
    kp = prepared_patient(task["patient"], scenario.patient.side, scenario.patient.posture,
                          float(task["voxel"]), X_BPt)
    controller = scenario.controller
    imager = km.Imager(kp, scenario.imaging, task["segmenter"], seed=int(task["seed"]))
    start_fraction, x_offset = 0.0, 0.0
    if task["study"] == "starts":
        start_fraction, x_offset = random_start(task, kp, controller)
    sweep = exploration(task, kp, imager, controller, start_fraction, x_offset)
    P = sweep.point_cloud()
    template = _template(scenario.localization.template)
    config = dataclasses.replace(scenario.localization, method=task["method"])
    loc = km.localize_cloud(kp, P, template, config, sweep.frames[0].X_BP.translation()[:2])
    result = {
        "run_id": run_id(task), "task": task, "mode": km.MODE,
        "patient": task["patient"], "er": task["er"], "start": task["start"],
        "start_fraction": start_fraction, "x_offset_mm": x_offset * 1e3,
        "explore_frames": len(sweep.frames), "explore_travel_mm": float(sweep.travel[-1] * 1e3),
        "points": int(len(P)),
        "e_trans_mm": e_trans(loc.X_BK, kp.X_BK_true) * 1e3,
        "e_rot_x_deg": math.degrees(e_rot_x(loc.X_BK, kp.X_BK_true)),
        "registration_ms": loc.compute_s * 1e3,
        "iterations": None if loc.result is None else int(loc.result.iterations),
        "localization_note": loc.note,
        "true_volume_ml": kp.kidney_volume * 1e6,
    }
    if task["study"] == "efficiency":
        export = task.get("export_dir")
        result["strategies"] = efficiency_of(
            kp, imager, controller, loc.X_BK, float(task.get("recon_spacing", 0.001)),
            export_dir=export, name=re.sub(r"[^A-Za-z0-9]+", "-", task["patient"]).strip("-"))
    result["wall_s"] = time.perf_counter() - t0
    return result


EXPORT_STRATEGIES = ("OP", "GT-OP")


def efficiency_of(kp, imager, controller, X_BK_est, recon_spacing: float, *,
                  export_dir=None, name: str = "patient") -> dict:
    """Per strategy: pole-to-pole curves (n, eps mm, V), totals, the whole sweep's totals,
    and the reconstructed kidney volume (mL) from the pole-to-pole masks. With
    ``export_dir``, the OP and GT-OP reconstructions are written there as NRRD (kidney
    probability, kidney mask and, for the classical/onnx segmenters, the grey volume)."""
    from drake_rus.experiments import kinematic as km
    from drake_rus.metrics.reconstruction import compound, reconstruct_kidney, write_nrrd
    out = {}
    for s in STRATEGY_ORDER:
        sweep = km.strategy_sweep(kp, imager, s, controller, X_BK_est, keep_images=True)
        p2p = sweep.pole_to_pole()
        c = km.sweep_curves(kp, p2p, imager.geometry)
        full = km.sweep_curves(kp, sweep, imager.geometry)
        entry = {
            "n": int(c["n_frames"]), "eps_mm": c["eps_total"] * 1e3, "V": c["V_final"],
            "n_full": int(full["n_frames"]), "eps_full_mm": full["eps_total"] * 1e3,
            "V_full": full["V_final"], "events": sweep.events,
            "curve_eps_mm": np.round(c["eps"] * 1e3, 3).tolist(),
            "curve_V": np.round(c["V"], 5).tolist(),
            "volume_ml": None, "volume_error_pct": None,
        }
        if p2p.frames:
            try:
                rec = reconstruct_kidney([f.mask for f in p2p.frames], p2p.poses,
                                         imager.geometry, spacing=recon_spacing)
                entry["volume_ml"] = rec["volume_ml"]
                entry["volume_error_pct"] = 100 * (rec["volume_ml"] / (kp.kidney_volume * 1e6)
                                                   - 1)
                if export_dir is not None and s in EXPORT_STRATEGIES:
                    d = Path(export_dir)
                    tag = f"{name}__{s}"
                    note = (f"drake-rus {s} sweep of {name}, kinematic mode; axes = robot base "
                            "frame x, y, z (mm)")
                    write_nrrd(d / f"{tag}__kidney_probability.nrrd",
                               rec["reconstruction"].values, rec["grid"], description=note)
                    write_nrrd(d / f"{tag}__kidney_mask.nrrd", rec["mask"], rec["grid"],
                               description=note)
                    if all(f.image is not None for f in p2p.frames):
                        grey = compound([f.image for f in p2p.frames], p2p.poses,
                                        imager.geometry, rec["grid"])
                        write_nrrd(d / f"{tag}__grey.nrrd", grey.values, rec["grid"],
                                   description=note)
                    entry["nrrd"] = sorted(str(p.name) for p in d.glob(f"{tag}__*.nrrd"))
            except ValueError as e:
                entry["volume_note"] = str(e)
        out[s] = entry
    return out


# ------------------------------------------------------------------------------- runner
def result_path(out_dir, task: dict) -> Path:
    return Path(out_dir) / "runs" / f"{run_id(task)}.json"


def load_results(out_dir, study: str | None = None) -> list[dict]:
    """All finished run results under ``out_dir/runs`` (optionally of one study)."""
    rows = []
    for p in sorted((Path(out_dir) / "runs").glob("*.json")):
        r = json.loads(p.read_text())
        if study is None or r["task"]["study"] == study:
            rows.append(r)
    return rows


def _json_default(o):
    if isinstance(o, np.generic):      # numpy scalars: int, float, bool
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _task_id(task: dict) -> str:
    return task["run_id"] if "run_id" in task else run_id(task)


def run_tasks(tasks: list[dict], out_dir, *, workers: int = 2, scheduler: str | None = None,
              progress: bool = True, desc: str = "runs", function=None, path_of=None,
              on_result=None) -> dict:
    """Runs the ``tasks`` not yet done under ``out_dir/runs`` and writes each result
    (atomically) as it finishes. ``scheduler``: address of an existing Dask scheduler;
    otherwise an embedded LocalCluster of ``workers`` single-threaded processes, or, with
    ``workers`` = 0, in this process. Returns {done, skipped, failed: [(run_id, error)]}.

    The study runs by default; another campaign passes its own picklable ``function``
    (task -> JSON-ready dict), ``path_of`` (out_dir, task -> result file) and, optionally,
    ``on_result`` (called with each saved result, e.g. to print a line)."""
    from tqdm import tqdm
    function = function or run_task
    path_of = path_of or result_path
    todo = [t for t in tasks if not path_of(out_dir, t).exists()]
    skipped = len(tasks) - len(todo)
    failed = []
    bar = tqdm(total=len(tasks), initial=skipped, desc=desc, unit="run", disable=not progress,
               dynamic_ncols=True)

    def save(task, result):
        write_text_atomic(path_of(out_dir, task), json.dumps(result, default=_json_default))
        bar.update(1)
        if on_result is not None:
            on_result(result)

    try:
        if not todo:
            return {"done": 0, "skipped": skipped, "failed": failed}
        if scheduler is None and workers == 0:
            for task in todo:
                try:
                    save(task, function(task))
                except Exception as e:    # noqa: BLE001 - report, keep going
                    failed.append((_task_id(task), f"{type(e).__name__}: {e}"))
            return {"done": len(todo) - len(failed), "skipped": skipped, "failed": failed}
        from distributed import Client, LocalCluster, as_completed
        cluster = None
        if scheduler is None:
            if workers < 0:
                raise ValueError(f"--workers: expected 0 or more, got {workers}")
            for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
                os.environ.setdefault(var, "1")
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                   dashboard_address=":0", silence_logs=40)
            client = Client(cluster)
        else:
            client = Client(scheduler)
        try:
            # Patient-major order: a worker tends to get the same patient's runs (cache).
            futures = {client.submit(function, t, pure=False, key=f"run-{_task_id(t)}"): t
                       for t in todo}
            for fut in as_completed(futures):
                task = futures[fut]
                try:
                    save(task, fut.result())
                except Exception as e:    # noqa: BLE001
                    failed.append((_task_id(task), f"{type(e).__name__}: {e}"))
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
        return {"done": len(todo) - len(failed), "skipped": skipped, "failed": failed}
    finally:
        bar.close()


# ------------------------------------------------------------------------------- analysis
def _paired_p(a, b) -> float:
    """Two-sided paired t-test p-value; 1.0 when the differences are all zero."""
    from scipy.stats import ttest_rel
    a, b = np.asarray(a, float), np.asarray(b, float)
    if len(a) < 2:
        return float("nan")
    d = a - b
    if np.allclose(d, d[0]) and np.allclose(d, 0):
        return 1.0
    p = float(ttest_rel(a, b).pvalue)
    return 1.0 if not np.isfinite(p) else p


def _mean_sd(v) -> tuple[float, float]:
    v = np.asarray([x for x in v if x is not None], float)
    if len(v) == 0:
        return float("nan"), float("nan")
    return float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else 0.0


def analyze_er_sweep(results: list[dict], alpha: float = 0.05) -> dict:
    """Per ER: mean/SD of both errors, paired p-values against ER 100%; the critical ER."""
    by = {}
    for r in results:
        by.setdefault(round(r["er"], 3), {})[r["patient"]] = r
    ers = sorted(by)
    if not ers:
        raise ValueError("er-sweep: no results")
    ref_er = max(ers)
    ref = by[ref_er]
    rows = []
    for er in ers:
        common = sorted(set(by[er]) & set(ref))
        et = [by[er][p]["e_trans_mm"] for p in common]
        erx = [by[er][p]["e_rot_x_deg"] for p in common]
        rows.append({
            "er": er, "n": len(common),
            "e_trans_mm_mean": _mean_sd(et)[0], "e_trans_mm_sd": _mean_sd(et)[1],
            "e_rot_x_deg_mean": _mean_sd(erx)[0], "e_rot_x_deg_sd": _mean_sd(erx)[1],
            "p_e_trans": _paired_p(et, [ref[p]["e_trans_mm"] for p in common]),
            "p_e_rot_x": _paired_p(erx, [ref[p]["e_rot_x_deg"] for p in common]),
            "registration_ms_mean": _mean_sd([by[er][p]["registration_ms"] for p in common])[0],
            "points_mean": _mean_sd([by[er][p]["points"] for p in common])[0],
        })
    critical = ref_er
    for row in reversed(rows):
        ok = (row["p_e_trans"] > alpha or not np.isfinite(row["p_e_trans"])) and \
             (row["p_e_rot_x"] > alpha or not np.isfinite(row["p_e_rot_x"]))
        if not ok:
            break
        critical = row["er"]
    first_ok = next((r["er"] for r in rows if r["p_e_trans"] > alpha and r["p_e_rot_x"] > alpha),
                    ref_er)
    return {"rows": rows, "critical_er": critical, "first_not_significant_er": first_ok,
            "reference_er": ref_er, "alpha": alpha}


def analyze_starts(results: list[dict], alpha: float = 0.05) -> dict:
    """Pairwise paired t-tests between starts over patients, Bonferroni-corrected."""
    by = {}
    for r in results:
        by.setdefault(int(r["start"]), {})[r["patient"]] = r
    starts = sorted(by)
    pairs = [(a, b) for i, a in enumerate(starts) for b in starts[i + 1:]]
    m = max(1, len(pairs))
    tests = []
    for a, b in pairs:
        common = sorted(set(by[a]) & set(by[b]))
        row = {"start_a": a, "start_b": b, "n": len(common)}
        for key in ("e_trans_mm", "e_rot_x_deg"):
            p = _paired_p([by[a][q][key] for q in common], [by[b][q][key] for q in common])
            row[f"p_{key}"] = p
            row[f"significant_{key}"] = bool(p < alpha / m)
        tests.append(row)
    per_start = []
    for s in starts:
        vals = list(by[s].values())
        per_start.append({"start": s, "n": len(vals),
                          "e_trans_mm_mean": _mean_sd([v["e_trans_mm"] for v in vals])[0],
                          "e_trans_mm_sd": _mean_sd([v["e_trans_mm"] for v in vals])[1],
                          "e_rot_x_deg_mean": _mean_sd([v["e_rot_x_deg"] for v in vals])[0],
                          "e_rot_x_deg_sd": _mean_sd([v["e_rot_x_deg"] for v in vals])[1]})
    allv = [r for r in results]
    return {"per_start": per_start, "tests": tests, "bonferroni_threshold": alpha / m,
            "any_significant": any(t["significant_e_trans_mm"] or t["significant_e_rot_x_deg"]
                                   for t in tests),
            "e_trans_mm": _mean_sd([r["e_trans_mm"] for r in allv]),
            "e_rot_x_deg": _mean_sd([r["e_rot_x_deg"] for r in allv])}


def analyze_efficiency(results: list[dict], alpha: float = 0.05) -> dict:
    """Totals per strategy, OP against the others (paired, Bonferroni), volume errors."""
    results = sorted(results, key=lambda r: r["patient"])
    per = {s: {"n": [], "eps_mm": [], "V": [], "volume_error_pct": []} for s in STRATEGY_ORDER}
    for r in results:
        for s in STRATEGY_ORDER:
            e = r["strategies"][s]
            per[s]["n"].append(e["n"])
            per[s]["eps_mm"].append(e["eps_mm"])
            per[s]["V"].append(e["V"])
            per[s]["volume_error_pct"].append(e["volume_error_pct"])
    summary = {}
    for s in STRATEGY_ORDER:
        summary[s] = {k: _mean_sd(v) for k, v in per[s].items()}
        ve = [abs(x) for x in per[s]["volume_error_pct"] if x is not None]
        summary[s]["abs_volume_error_pct"] = _mean_sd(ve)
        summary[s]["within_5pct"] = int(sum(x <= 5 for x in ve))
    others = [s for s in STRATEGY_ORDER if s != "OP"]
    m = 2 * len(others)
    comparisons = []
    for s in others:
        for key in ("n", "eps_mm"):
            a, b = np.asarray(per["OP"][key], float), np.asarray(per[s][key], float)
            p = _paired_p(a, b)
            comparisons.append({
                "comparison": f"OP vs {s}", "metric": key,
                "reduction_mean": float(np.mean(b - a)) if len(a) else float("nan"),
                "reduction_sd": float(np.std(b - a, ddof=1)) if len(a) > 1 else 0.0,
                "op_lower_count": int(np.sum(a < b)), "patients": int(len(a)),
                "p": p, "significant": bool(p < alpha / m)})
    return {"per_patient": per, "summary": summary, "comparisons": comparisons,
            "bonferroni_threshold": alpha / m, "patients": [r["patient"] for r in results]}


def mean_curve(results: list[dict], strategy: str, x_key: str, grid: np.ndarray) -> np.ndarray:
    """Mean over patients of V as a function of n (x_key "n") or eps (mm, "eps"), each
    patient's curve held at its final V past its end."""
    curves = []
    for r in results:
        e = r["strategies"][strategy]
        V = np.asarray(e["curve_V"], float)
        if len(V) == 0:
            curves.append(np.zeros_like(grid))
            continue
        x = np.arange(1, len(V) + 1, dtype=float) if x_key == "n" else np.asarray(
            e["curve_eps_mm"], float)
        curves.append(np.interp(grid, x, V, left=0.0, right=V[-1]))
    return np.mean(curves, axis=0) if curves else np.zeros_like(grid)


# ------------------------------------------------------------------------------- outputs
def _csv(path, rows: list[dict]) -> Path:
    """Writes ``rows`` (dicts with the same keys) as CSV, atomically."""
    import csv
    import io
    buf = io.StringIO()
    if rows:
        w = csv.DictWriter(buf, fieldnames=list(rows[0]))
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    return write_text_atomic(path, buf.getvalue())


def _save_fig(fig, path) -> Path:
    from drake_rus.io_utils import atomic_path
    import matplotlib.pyplot as plt
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return Path(path)


MODE_NOTE = "kinematic mode (planned probe poses, no robot dynamics)"


def plot_er_sweep(analysis: dict, path) -> Path:
    """Fig. 7d: E_trans and E_rot,x against ER, mean +- SD across patients."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows = analysis["rows"]
    er = np.array([r["er"] for r in rows]) * 100
    fig, axes = plt.subplots(2, 1, figsize=(6, 6), sharex=True)
    for ax, key, unit, paper in ((axes[0], "e_trans_mm", "mm", PAPER["er_sweep"]["e_trans_mm_at_60"]),
                                 (axes[1], "e_rot_x_deg", "deg",
                                  PAPER["er_sweep"]["e_rot_x_deg_at_60"])):
        m = np.array([r[f"{key}_mean"] for r in rows])
        s = np.array([r[f"{key}_sd"] for r in rows])
        ax.plot(er, m, "o-", label="ours (mean)")
        ax.fill_between(er, m - s, m + s, alpha=0.25, label="+- SD")
        ax.errorbar([60], [paper[0]], yerr=[paper[1]], fmt="s", color="k", capsize=4,
                    label="seed paper at ER 60%")
        ax.axvline(analysis["critical_er"] * 100, color="g", ls="--",
                   label=f"critical ER {analysis['critical_er'] * 100:.0f}%")
        ax.set_ylabel(f"{'E_trans' if unit == 'mm' else 'E_rot,x'} ({unit})")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    axes[1].set_xlabel("exploration ratio ER (%)")
    fig.suptitle(f"Localization vs exploration ratio (Fig. 7d), {MODE_NOTE}", fontsize=8)
    fig.tight_layout()
    return _save_fig(fig, path)


def plot_starts(results: list[dict], analysis: dict, path) -> Path:
    """Fig. 9d: box plots of both errors per random start."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    starts = [r["start"] for r in analysis["per_start"]]
    fig, axes = plt.subplots(2, 1, figsize=(6, 6), sharex=True)
    for ax, key, label in ((axes[0], "e_trans_mm", "E_trans (mm)"),
                           (axes[1], "e_rot_x_deg", "E_rot,x (deg)")):
        data = [[r[key] for r in results if r["start"] == s] for s in starts]
        ax.boxplot(data, tick_labels=[f"start {s + 1}" for s in starts])
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    er = results[0]["er"] if results else float("nan")
    fig.suptitle(f"Random exploration starts at ER {er * 100:.0f}% (Fig. 9d), {MODE_NOTE}; "
                 f"Bonferroni p < {analysis['bonferroni_threshold']:.4f}", fontsize=8)
    fig.tight_layout()
    return _save_fig(fig, path)


COLORS = {"OP": "tab:red", "GT-OP": "tab:green", "NOP": "tab:blue", "SL": "tab:orange"}


def plot_efficiency(results: list[dict], analysis: dict, path) -> Path:
    """Fig. 10e-h (+ volume error): mean V against n and eps, box plots of totals."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, 3, figsize=(13, 7.5))
    per = analysis["per_patient"]
    n_max = max([max(per[s]["n"]) for s in STRATEGY_ORDER if per[s]["n"]] + [2])
    e_max = max([max(per[s]["eps_mm"]) for s in STRATEGY_ORDER if per[s]["eps_mm"]] + [1.0])
    n_grid = np.linspace(1, n_max, 200)
    e_grid = np.linspace(0, e_max, 200)
    for s in STRATEGY_ORDER:
        axes[0, 0].plot(n_grid, mean_curve(results, s, "n", n_grid), color=COLORS[s], label=s)
        axes[0, 1].plot(e_grid, mean_curve(results, s, "eps", e_grid), color=COLORS[s], label=s)
    axes[0, 0].set(xlabel="US frame count n", ylabel="volume ratio V (mean)",
                   title="(e) V vs n")
    axes[0, 1].set(xlabel="imaging-window path length eps (mm)", ylabel="V (mean)",
                   title="(f) V vs eps")
    axes[0, 0].legend()
    for ax, key, label, title in ((axes[1, 0], "n", "total frames n", "(g) total n"),
                                  (axes[1, 1], "eps_mm", "total eps (mm)", "(h) total eps")):
        ax.boxplot([per[s][key] for s in STRATEGY_ORDER], tick_labels=list(STRATEGY_ORDER))
        ax.set_ylabel(label)
        ax.set_title(title)
    vol = [[v for v in per[s]["volume_error_pct"] if v is not None] for s in STRATEGY_ORDER]
    axes[1, 2].boxplot(vol, tick_labels=list(STRATEGY_ORDER))
    axes[1, 2].axhspan(-5, 5, color="g", alpha=0.1, label="+-5%")
    axes[1, 2].set(ylabel="reconstructed - true volume (%)", title="kidney volume error")
    axes[1, 2].legend(fontsize=7)
    # Per patient: OP's totals against NOP's and SL's.
    ax = axes[0, 2]
    x = np.arange(len(analysis["patients"]))
    for s in STRATEGY_ORDER:
        ax.plot(x, per[s]["eps_mm"], "o-", color=COLORS[s], label=s, ms=3)
    ax.set(xlabel="patient", ylabel="total eps (mm)", title="eps per patient")
    ax.set_xticks(x)
    ax.set_xticklabels([p.split(":")[-1] for p in analysis["patients"]], fontsize=7)
    for a in axes.ravel():
        a.grid(alpha=0.3)
    fig.suptitle(f"Sweep efficiency by strategy (Fig. 10e-h), pole to pole, {MODE_NOTE}",
                 fontsize=9)
    fig.tight_layout()
    return _save_fig(fig, path)


def write_er_sweep_outputs(out_dir, results) -> dict:
    out = Path(out_dir)
    analysis = analyze_er_sweep(results)
    _csv(out / "er_sweep_runs.csv", [_flat(r) for r in results])
    _csv(out / "er_sweep_table.csv", analysis["rows"])
    plot_er_sweep(analysis, out / "fig7d_er_sweep.png")
    write_text_atomic(out / "er_sweep.json", json.dumps(analysis, default=_json_default, indent=1))
    return analysis


def write_starts_outputs(out_dir, results) -> dict:
    out = Path(out_dir)
    analysis = analyze_starts(results)
    _csv(out / "starts_runs.csv", [_flat(r) for r in results])
    _csv(out / "starts_tests.csv", analysis["tests"])
    plot_starts(results, analysis, out / "fig9d_starts.png")
    write_text_atomic(out / "starts.json", json.dumps(analysis, default=_json_default, indent=1))
    return analysis


def write_efficiency_outputs(out_dir, results) -> dict:
    out = Path(out_dir)
    analysis = analyze_efficiency(results)
    rows = []
    for r in results:
        for s in STRATEGY_ORDER:
            e = r["strategies"][s]
            rows.append({"patient": r["patient"], "strategy": s, "n": e["n"],
                         "eps_mm": e["eps_mm"], "V": e["V"], "n_full": e["n_full"],
                         "eps_full_mm": e["eps_full_mm"], "volume_ml": e["volume_ml"],
                         "true_volume_ml": r["true_volume_ml"],
                         "volume_error_pct": e["volume_error_pct"],
                         "e_trans_mm": r["e_trans_mm"], "e_rot_x_deg": r["e_rot_x_deg"]})
    _csv(out / "efficiency_runs.csv", rows)
    _csv(out / "efficiency_tests.csv", analysis["comparisons"])
    plot_efficiency(results, analysis, out / "fig10_efficiency.png")
    write_text_atomic(out / "efficiency.json",
                      json.dumps({k: v for k, v in analysis.items() if k != "per_patient"},
                                 default=_json_default, indent=1))
    return analysis


def _flat(r: dict) -> dict:
    keys = ("patient", "er", "start", "start_fraction", "x_offset_mm", "explore_frames",
            "explore_travel_mm", "points", "e_trans_mm", "e_rot_x_deg", "registration_ms",
            "iterations", "wall_s")
    return {k: r.get(k) for k in keys}


# ------------------------------------------------------------------------------- report
def _where(i: dict) -> str:
    if i.get("scheduler"):
        return f"Dask scheduler {i['scheduler']}"
    if not i.get("workers"):
        return "in one process"
    return f"embedded LocalCluster, {i['workers']} worker(s)"


def _runs(i: dict) -> str:
    if i.get("runs_done") is None:
        return "all runs; "
    return f"{i['runs_done']} runs run, {i['runs_skipped']} skipped; "


def _p(x):
    """A p-value: 4 decimals, or scientific notation below 1e-4."""
    if x is None or not np.isfinite(x):
        return "n/a"
    return f"{x:.4f}" if x >= 1e-4 else f"{x:.1e}"


def _f(x, nd=2):
    return "n/a" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f"{x:.{nd}f}"


def report_markdown(meta: dict, er: dict | None, starts: dict | None, eff: dict | None,
                    closed: list | None = None) -> str:
    """report.md: our numbers beside the seed paper's for each table and figure."""
    L = [f"# drake-rus studies: the seed paper's section III on our virtual cohort", "",
         f"- Patients: {', '.join(meta['patients'])} ({len(meta['patients'])})",
         f"- Mode: **{MODE_NOTE}** for every run of the tables and figures; "
         + (f"{len(closed)} closed-loop dynamic scan(s) only in the closed-loop check."
            if closed else "no closed-loop dynamic runs."),
         f"- Segmenter: {meta['segmenter']}; localization method: `{meta['method']}`; "
         f"label voxel {meta['voxel'] * 1e3:.0f} mm; study seed {meta['seed']}.",
         f"- Starts and efficiency ran at ER {meta.get('er', float('nan')) * 100:.0f}% (the "
         f"critical ER of this sweep when it ran).", "- Wall time per invocation (resumed "
         "invocations skip finished runs): " + "; ".join(
             f"{i['wall_s']:.0f} s ({_runs(i)}{_where(i)}; stages "
             + ", ".join(f"{k} {v:.0f} s" for k, v in (i.get("stage_wall_s") or {}).items())
             + ")"
             for i in meta.get("invocations", [meta])), ""]
    if er is not None:
        p = PAPER["er_sweep"]
        L += ["## Exploration ratio vs localization (Fig. 7d, `fig7d_er_sweep.png`)", "",
              "| ER | E_trans (mm) | E_rot,x (deg) | p (E_trans vs 100%) | p (E_rot,x vs 100%) |",
              "|---|---|---|---|---|"]
        for r in er["rows"]:
            L.append(f"| {r['er'] * 100:.0f}% | {_f(r['e_trans_mm_mean'])} +- "
                     f"{_f(r['e_trans_mm_sd'])} | {_f(r['e_rot_x_deg_mean'])} +- "
                     f"{_f(r['e_rot_x_deg_sd'])} | {_p(r['p_e_trans'])} | "
                     f"{_p(r['p_e_rot_x'])} |")
        row60 = next((r for r in er["rows"] if abs(r["er"] - 0.6) < 1e-6), None)
        L += ["", f"Critical ER (smallest ER from which on no ER differs from 100% at p > 0.05 "
              f"in either error): **ours {er['critical_er'] * 100:.0f}%**, paper "
              f"{p['critical_er'] * 100:.0f}% (p = {p['p_e_trans_at_60']} and "
              f"{p['p_e_rot_at_60']} at 60%). First ER with both p > 0.05: "
              f"{er['first_not_significant_er'] * 100:.0f}%."]
        if row60:
            L.append(f"At ER 60%: ours {_f(row60['e_trans_mm_mean'])} +- "
                     f"{_f(row60['e_trans_mm_sd'])} mm, {_f(row60['e_rot_x_deg_mean'])} +- "
                     f"{_f(row60['e_rot_x_deg_sd'])} deg; paper {p['e_trans_mm_at_60'][0]} +- "
                     f"{p['e_trans_mm_at_60'][1]} mm, {p['e_rot_x_deg_at_60'][0]} +- "
                     f"{p['e_rot_x_deg_at_60'][1]} deg.")
        L.append("")
    if starts is not None:
        pl = PAPER["localization"]
        L += ["## Random exploration starts (Fig. 9d, `fig9d_starts.png`)", "",
              f"All runs: E_trans {_f(starts['e_trans_mm'][0])} +- {_f(starts['e_trans_mm'][1])}"
              f" mm, E_rot,x {_f(starts['e_rot_x_deg'][0])} +- {_f(starts['e_rot_x_deg'][1])} "
              f"deg (paper, 15 patients x 5 starts: {pl['e_trans_mm'][0]} +- "
              f"{pl['e_trans_mm'][1]} mm, {pl['e_rot_x_deg'][0]} +- {pl['e_rot_x_deg'][1]} deg).",
              "", "| start | E_trans (mm) | E_rot,x (deg) |", "|---|---|---|"]
        for r in starts["per_start"]:
            L.append(f"| {r['start'] + 1} | {_f(r['e_trans_mm_mean'])} +- {_f(r['e_trans_mm_sd'])}"
                     f" | {_f(r['e_rot_x_deg_mean'])} +- {_f(r['e_rot_x_deg_sd'])} |")
        n_sig = sum(t["significant_e_trans_mm"] + t["significant_e_rot_x_deg"]
                    for t in starts["tests"])
        pmin = min([min(t["p_e_trans_mm"], t["p_e_rot_x_deg"]) for t in starts["tests"]]
                   or [float("nan")])
        L += ["", f"Pairwise paired t-tests ({len(starts['tests'])} pairs x 2 errors, "
              f"Bonferroni threshold p < {starts['bonferroni_threshold']:.4f}): "
              f"**{n_sig} significant** (smallest p = {_p(pmin)}). Paper: "
              f"{PAPER['starts']}.", ""]
    if eff is not None:
        s = eff["summary"]
        pe = PAPER["efficiency"]
        L += ["## Sweep efficiency (Fig. 10, `fig10_efficiency.png`)", "",
              "Pole to pole (from the first to the last frame showing the kidney; for a pivot, "
              "its second leg, which runs from one pole to the other).", "",
              "| strategy | n | eps (mm) | V | volume error (%) | abs volume error (%) |",
              "|---|---|---|---|---|---|"]
        for k in STRATEGY_ORDER:
            L.append(f"| {k} | {_f(s[k]['n'][0], 1)} +- {_f(s[k]['n'][1], 1)} | "
                     f"{_f(s[k]['eps_mm'][0], 1)} +- {_f(s[k]['eps_mm'][1], 1)} | "
                     f"{_f(s[k]['V'][0], 3)} | {_f(s[k]['volume_error_pct'][0])} +- "
                     f"{_f(s[k]['volume_error_pct'][1])} | "
                     f"{_f(s[k]['abs_volume_error_pct'][0])} (within 5%: "
                     f"{s[k]['within_5pct']}/{len(eff['patients'])}) |")
        L += ["", "| comparison | metric | reduction by OP (mean +- SD) | OP lower on | p | "
              "significant (Bonferroni) |", "|---|---|---|---|---|---|"]
        for c in eff["comparisons"]:
            unit = " mm" if c["metric"] == "eps_mm" else " frames"
            L.append(f"| {c['comparison']} | {c['metric']} | {_f(c['reduction_mean'], 1)} +- "
                     f"{_f(c['reduction_sd'], 1)}{unit} | {c['op_lower_count']}/{c['patients']} | "
                     f"{_p(c['p'])} | {c['significant']} |")
        L += ["", f"Paper (simulation, 15 patients): OP reduced eps by {pe['eps_reduction_vs_SL_mm'][0]}"
              f" +- {pe['eps_reduction_vs_SL_mm'][1]} mm against SL and by "
              f"{pe['eps_reduction_vs_NOP_mm'][0]} +- {pe['eps_reduction_vs_NOP_mm'][1]} mm "
              f"against NOP; localization error cost {pe['eps_extra_vs_GT_OP_mm'][0]} +- "
              f"{pe['eps_extra_vs_GT_OP_mm'][1]} mm against GT-OP. Volume: "
              f"{PAPER['volume_loa']}; our target: GT-OP within 5%.", ""]
    if closed:
        L += ["## Closed-loop check (a few dynamic scans beside their kinematic twins)", "",
              "Same patient, start (10% into the E-ROI), ER, segmenter and localization; "
              "n, eps and V over both pivot legs (as the scan's `ScanMetrics` counts them).", "",
              "| patient | mode | status | E_trans (mm) | E_rot,x (deg) | n | eps (mm) | V | "
              "wall (s) |", "|---|---|---|---|---|---|---|---|---|"]
        for r in closed:
            c, k = r["closed_loop"], r["kinematic"]
            L.append(f"| {r['patient']} | closed-loop | {c['status']} | {_f(c['e_trans_mm'])} | "
                     f"{_f(c['e_rot_x_deg'])} | {c['n']} | {_f(c['eps_mm'], 1)} | "
                     f"{_f(c['V'], 3)} | {_f(c['wall_s'], 0)} (sim {_f(c['sim_s'], 1)} s) |")
            L.append(f"| {r['patient']} | kinematic | - | {_f(k['e_trans_mm'])} | "
                     f"{_f(k['e_rot_x_deg'])} | {k['n']} | {_f(k['eps_mm'], 1)} | "
                     f"{_f(k['V'], 3)} | {_f(k['wall_s'], 0)} |")
        L.append("")
    L += ["## Method notes", "",
          "- Kinematic runs place the probe exactly where the controller laws ask (eq. 17 "
          "exploration, eq. 20-23 pivot), tip on the skin surface; no contact dynamics, "
          "tracking error or tissue compression.",
          "- Exploration starts at the E-ROI's superior end (ER sweep, efficiency) or at a "
          "seeded random point inside the E-ROI (starts). ER 0% uses the initial alignment "
          "alone (heuristic rotation, centroid under the start point).",
          "- NOP uses the true kidney pose (the in-vivo NOP was expert-placed); OP the "
          "registered pose; SL is the exploration controller over the whole kidney.",
          "- V (eq. 25): fraction of the true kidney's 2 mm voxels inside the fan and the "
          "elevational slab of at least one frame (`drake_rus/metrics/core.py`).",
          "- Kidney volume: masks compounded at 1 mm (nearest-pixel, fan clipping, hole "
          "filling), threshold 0.5, against the kidney mesh's volume.", ""]
    return "\n".join(L)


def write_closed_loop_outputs(out_dir, results) -> Path:
    """closed_loop.csv: each closed-loop scan beside its kinematic twin."""
    rows = []
    for r in results:
        for mode in ("closed_loop", "kinematic"):
            e = r[mode]
            rows.append({"patient": r["patient"], "mode": mode, "er": r["er"],
                         "status": e.get("status", ""), "e_trans_mm": e["e_trans_mm"],
                         "e_rot_x_deg": e["e_rot_x_deg"], "n": e["n"], "eps_mm": e["eps_mm"],
                         "V": e["V"], "wall_s": e["wall_s"], "sim_s": e.get("sim_s")})
    return _csv(Path(out_dir) / "closed_loop.csv", rows)
