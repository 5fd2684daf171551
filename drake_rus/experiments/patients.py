"""A study run's patient and where on it the run starts, the same in both run modes.

- :func:`prepared_patient`: the kinematic patient (label volume, skin heights, true kidney
  pose), cached per process; :func:`task_scenario_and_patient`: a run's scenario and its
  patient placed on the bed.
- The ER (``StudyTask.er_unit``): ``kidney`` (default, the paper's simulation, III-C: "the
  fraction of total kidney length traversed by the probe") explores ER x the patient's
  kidney length along the exploration line (the E-ROI's length along base y,
  :func:`kidney_length`); ``fixed`` explores ER x L_m (``controller.kidney_length``,
  100 mm: the paper's in-vivo rule, III-F): :func:`exploration_travel`.
- Random starts (the ``starts`` study, III-D): five per patient inside the E-ROI (start
  fraction along y leaving room for the whole ER travel, at least
  :data:`START_MIN_ROOM`, and an x offset within the middle half of the E-ROI's width),
  drawn again until the kidney is visible at the start (the
  paper's II-A assumption (i), :func:`start_visibility`): :func:`visible_random_start`.
"""

from __future__ import annotations

import zlib

import numpy as np

from drake_rus.anatomy import load_patient
from drake_rus.experiments import kinematic as km
from drake_rus.experiments.keys import task_scenario
from drake_rus.experiments.specs import ER_UNITS, StudyTask

# Random starts are drawn where the kidney is visible (the paper's II-A (i)), checked at the
# start and this far (m) around it (the closed loop lands within 2 mm), at most this often.
START_VISIBILITY_TOLERANCE = 0.002
START_MAX_DRAWS = 200
# The least room (fraction of the E-ROI's length) random starts are drawn in. At ER 100%
# the travel leaves none: every start would lie on the E-ROI's end, where the pole is not
# yet in view (the paper's II-A (i) cannot hold; a starts study at a critical ER of 100%
# failed on every draw). The start may then lie up to this far into the E-ROI and the
# exploration runs as far past the other pole, where it sees no more kidney.
START_MIN_ROOM = 0.1


def kidney_length(kp) -> float:
    """The patient's kidney length (m) along the exploration line (base y): the E-ROI's
    length, i.e. the travel that takes the transverse view from one pole to the other."""
    return float(kp.roi.length_y)


def exploration_travel(er: float, unit: str, patient_length: float, L_m: float) -> float:
    """Travel (m) of an exploration at ratio ``er``: er x the patient's kidney length
    (``unit`` "kidney") or er x L_m ("fixed")."""
    if unit == "kidney":
        return float(er) * float(patient_length)
    if unit == "fixed":
        return float(er) * float(L_m)
    raise ValueError(f"er_unit: expected one of {', '.join(ER_UNITS)}, got {unit!r}")


_PATIENTS: dict = {}


def prepared_patient(spec: str, side: str, posture: str, voxel: float, X_BPt):
    """Kinematic patient, cached per process (label volumes take seconds to build)."""
    key = (spec, side, posture, voxel, tuple(X_BPt.GetAsMatrix4().ravel()))
    if key not in _PATIENTS:
        if len(_PATIENTS) >= 16:
            _PATIENTS.pop(next(iter(_PATIENTS)))
        patient = load_patient(spec, side=side, posture=posture, voxel_size=voxel, progress=False)
        _PATIENTS[key] = km.prepare_patient(patient, X_BPt)
    return _PATIENTS[key]


def task_scenario_and_patient(task: StudyTask):
    """(scenario, prepared patient) of a study task: the task's scenario with its overrides
    and posture, and the patient placed on the bed at that scenario's X_BPt."""
    scenario = task_scenario(task)
    kp = prepared_patient(
        task.patient,
        scenario.patient.side,
        scenario.patient.posture,
        float(task.voxel),
        scenario.patient.X_BPt.GetDeterministicValue(),
    )
    return scenario, kp


def random_start(
    task: StudyTask, kp, controller, visible=None, max_draws: int = START_MAX_DRAWS
) -> tuple[float, float]:
    """(start_fraction, x_offset) of random start ``task.start`` (deterministic in the
    study seed, the patient and the start index): the start fraction along the E-ROI leaves
    room for the whole ER travel (at least :data:`START_MIN_ROOM`: at ER 100% a start may
    lie that far in, the travel running as far past the far pole), the x offset lies within
    the middle half of its width.
    With ``visible`` (a callable (x, y) -> bool, e.g. :func:`start_visibility`) draws are
    repeated, from the same random stream, until the kidney is visible at the start (the
    paper's assumption II-A (i)); :func:`visible_random_start` also says how many were
    rejected."""
    return visible_random_start(task, kp, controller, visible, max_draws)[:2]


def visible_random_start(
    task: StudyTask, kp, controller, visible=None, max_draws: int = START_MAX_DRAWS
) -> tuple[float, float, int]:
    """:func:`random_start` and the number of draws rejected because ``visible`` said the
    kidney is not in the image there. Raises ValueError when no draw of ``max_draws`` is
    visible (the E-ROI shows no kidney where the exploration could start)."""
    rng = np.random.default_rng(
        [int(task.seed), zlib.crc32(str(task.patient).encode()), int(task.start)]
    )
    travel = exploration_travel(task.er, task.er_unit, kidney_length(kp), controller.kidney_length)
    room = max(START_MIN_ROOM, 1.0 - travel / max(kp.roi.length_y, 1e-9))
    width = kp.roi.x_max - kp.roi.x_min
    for draw in range(max(1, int(max_draws))):
        sf, xo = float(rng.uniform(0.0, room)), float(rng.uniform(-0.25, 0.25) * width)
        if visible is None or visible(km.start_xy(kp, sf, controller.scan_direction, xo)):
            return sf, xo, draw
    raise ValueError(
        f"random start {task.start} of {task.patient}: the kidney is not "
        f"visible at any of {max_draws} drawn starts"
    )


def start_visibility(kp, imager, tolerance: float = START_VISIBILITY_TOLERANCE):
    """A callable (x, y) -> bool: the kidney is visible (the segmenter's read-out, area >=
    ``imaging.min_kidney_area``) in the transverse frame with the tip on the skin at (x, y)
    and at (x +- ``tolerance``, y) and (x, y +- ``tolerance``): the paper's assumption II-A
    (i), "the robot starts where the kidney is visible", kept by the closed-loop scan, which
    lands within ``transit_position_tolerance`` (2 mm) of its start. The imager's frame
    counter and temporal prior are restored, so the exploration after it is unchanged."""
    d = float(tolerance)
    offsets = ((0.0, 0.0), (d, 0.0), (-d, 0.0), (0.0, d), (0.0, -d))

    def visible(xy) -> bool:
        index = imager.frame_index
        try:
            for dx, dy in offsets:
                imager.reset()
                X = km.tip_pose(kp, km.R_B_TRANSVERSE, float(xy[0]) + dx, float(xy[1]) + dy)
                if not imager(X).visible:
                    return False
            return True
        finally:
            imager.frame_index = index
            imager.reset()

    return visible
