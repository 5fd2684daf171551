"""The predicted-end pivot strategy (beyond the seed): the predicted end angles on analytic
cases and the supervisor's phase sequence (pre-tilt in TRANSIT, one sweep in PIVOT)."""

import dataclasses
import math

import numpy as np
import pytest
from pydrake.math import RollPitchYaw, RotationMatrix
from scipy.optimize import brentq

from drake_rus.control import supervisor
from drake_rus.control.config import ControllerConfig
from drake_rus.control.laws import pivot_end_angles

GEOM = dict(probe_radius=0.05, half_angle=math.radians(20.0), depth=0.15)
STEP = math.radians(0.1)


def sphere_points(r, n=6000, centre=(0.0, 0.0, 0.0), axes=None):
    """Fibonacci points on a sphere (or an axis-aligned ellipsoid with semi-axes ``axes``)."""
    k = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * k / n)
    th = math.pi * (1 + 5**0.5) * k
    u = np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], axis=1)
    scale = np.full(3, r) if axes is None else np.asarray(axes, float)
    return u * scale + np.asarray(centre, float)


def test_sphere_below_the_pivot_leaves_at_asin_of_radius_over_depth():
    r, h, D = 0.03, 0.005, 0.10
    pts = sphere_points(r)
    plus, minus = pivot_end_angles(
        np.eye(3),
        [0.5, 0.0, 0.0],
        pts,
        [0.5, 0.0, D],
        [0, 0, -1],
        [1, 0, 0],
        slab_half_width=h,
        max_angle=1.0,
        step=STEP,
        **GEOM,
    )
    expected = math.asin((r + h) / D)
    assert plus == pytest.approx(expected, abs=2 * STEP)
    assert minus == pytest.approx(-expected, abs=2 * STEP)


def test_offset_kidney_and_rotated_frames():
    """A sphere off the pivot's vertical (offset e along y_K), with K rotated about z and the
    pivot axis o along the kidney's x: ends at phi +- asin((r + h) / R0), phi = atan(e / D)."""
    r, h, D, e = 0.025, 0.005, 0.09, 0.015
    yaw = 0.7
    R_BK = RotationMatrix(RollPitchYaw(0.0, 0.0, yaw)).matrix()
    p_BK = np.array([0.55, 0.1, 0.02])
    pts = sphere_points(r, centre=(0.0, e, 0.0))
    o = R_BK[:, 0]
    pivot = p_BK + np.array([0.0, 0.0, D])
    plus, minus = pivot_end_angles(
        R_BK, p_BK, pts, pivot, [0, 0, -1], o, slab_half_width=h, max_angle=1.0, step=STEP, **GEOM
    )
    # y_P(theta) . c = D sin(theta) - e cos(theta) with y_B offset e along R_BK y.
    R0, phi = math.hypot(D, e), math.atan2(e, D)
    half = math.asin((r + h) / R0)
    assert plus == pytest.approx(phi + half, abs=2 * STEP)
    assert minus == pytest.approx(phi - half, abs=2 * STEP)


def test_ellipsoid_support_function():
    """Ellipsoid with semi-axes (a, b, c) centred at depth D: the plane through the pivot with
    normal y_P = (0, -cos, -sin) last touches it where D sin(theta) = sqrt(b^2 cos^2 +
    c^2 sin^2) + h."""
    a, b, c, h, D = 0.055, 0.03, 0.02, 0.004, 0.095
    pts = sphere_points(None, n=20000, axes=(a, b, c))
    plus, minus = pivot_end_angles(
        np.eye(3),
        np.zeros(3),
        pts,
        [0, 0, D],
        [0, 0, -1],
        [1, 0, 0],
        slab_half_width=h,
        max_angle=1.0,
        step=STEP,
        **GEOM,
    )
    f = lambda t: D * math.sin(t) - math.sqrt(b**2 * math.cos(t) ** 2 + c**2 * math.sin(t) ** 2) - h  # noqa: E731
    expected = brentq(f, 0.0, 1.2)
    assert plus == pytest.approx(expected, abs=3 * STEP)
    assert minus == pytest.approx(-expected, abs=3 * STEP)


def test_cap_and_fan_bounds():
    # Still imaged at the maximum tilt: the cap is returned.
    pts = sphere_points(0.08)
    plus, minus = pivot_end_angles(
        np.eye(3),
        np.zeros(3),
        pts,
        [0, 0, 0.09],
        [0, 0, -1],
        [1, 0, 0],
        slab_half_width=0.005,
        max_angle=0.4,
        **GEOM,
    )
    assert plus == pytest.approx(0.4) and minus == pytest.approx(-0.4)
    # Beyond the imaging depth: never imaged.
    deep = sphere_points(0.01, centre=(0, 0, -0.3))
    assert pivot_end_angles(
        np.eye(3),
        np.zeros(3),
        deep,
        [0, 0, 0.0],
        [0, 0, -1],
        [1, 0, 0],
        slab_half_width=0.005,
        max_angle=0.6,
        **GEOM,
    ) == (0.0, 0.0)
    # Outside the fan's lateral opening (far along the array): never imaged.
    side = sphere_points(0.005, centre=(0.1, 0, -0.05))
    assert pivot_end_angles(
        np.eye(3),
        np.zeros(3),
        side,
        [0, 0, 0.0],
        [0, 0, -1],
        [1, 0, 0],
        slab_half_width=0.005,
        max_angle=0.6,
        **GEOM,
    ) == (0.0, 0.0)


# ------------------------------------------------------------------ supervisor
def _cfg(**kw):
    kw.setdefault("contact_dwell", 0.0)
    return dataclasses.replace(ControllerConfig(), **kw)


def _inputs(t, p, R, visible=True, R_BK=None, p_BK=None, model=None):
    return supervisor.SupervisorInputs(
        t=t,
        R_BP=np.asarray(R),
        p_BP=np.asarray(p, float),
        F_z=9.0,
        kidney_visible=visible,
        c_msk=0.5,
        R_BK=R_BK,
        p_BK=p_BK,
        pivot_model=model,
    )


def _R_of(s):
    """The probe orientation that tracks a_des, o_des exactly."""
    a, o = s.a_des, s.o_des
    return np.column_stack([o, np.cross(a, o), a])


def _run(c, truth_ends, model, t_max=60.0):
    """From the start through LOCALIZE (kidney at p_BK, identity), TRANSIT and PIVOT with
    perfect tracking; the kidney is visible for tilts inside ``truth_ends``."""
    dt = 0.01
    R_down = np.diag([1.0, -1.0, -1.0])
    p_BK = np.array([0.55, 0.0, 0.0])
    tip = np.array([0.55, 0.0, 0.10])
    s = supervisor.SupervisorState()
    t = 0.0
    trace = []
    while s.phase not in (supervisor.Phase.DONE, supervisor.Phase.ABORT) and t < t_max:
        R = R_down if s.phase <= supervisor.Phase.LOCALIZE else _R_of(s)
        ang = s.pivot_angle if s.phase >= supervisor.Phase.TRANSIT else 0.0
        vis = truth_ends[1] < ang < truth_ends[0]
        s = supervisor.supervisor_step(
            s, _inputs(t, tip, R, visible=vis, R_BK=np.eye(3), p_BK=p_BK, model=model), c, dt
        )
        trace.append((s.phase, s.pivot_angle, s.pretilt_stage))
        t += dt
    return s, trace


def _model(r=0.03, centre=(0.0, 0.0, 0.0)):
    return supervisor.PivotModel(
        points_K=sphere_points(r, centre=centre), slab_half_width=0.005, **GEOM
    )


def test_predicted_end_strategy_phase_sequence():
    c = _cfg(
        exploration_ratio=0.02,
        localize_hold_time=0.0,
        pivot_rate=0.2,
        max_pivot_tilt=0.6,
        visibility_debounce=0.05,
        pivot_strategy="predicted_end",
        pivot_end_margin=0.05,
        pretilt_rate=0.3,
    )
    model = _model(centre=(0.0, 0.01, 0.0))  # off-centre: the minus side is nearer
    R0, phi = math.hypot(0.1, 0.01), math.atan2(0.01, 0.1)
    half = math.asin(0.035 / R0)
    truth = (phi + half - 0.02, phi - half + 0.02)  # the kidney leaves a bit earlier
    s, trace = _run(c, truth, model)
    assert s.phase == supervisor.Phase.DONE, s.events
    plus, minus = s.pivot_ends
    assert plus == pytest.approx(phi + half, abs=0.01)
    assert minus == pytest.approx(phi - half, abs=0.01)
    assert s.pretilt_side == -1.0
    # Phases in order, the pre-tilt happens in TRANSIT (stage 1 then 2), never in PIVOT.
    phases = [ph for ph, _, _ in trace]
    order = [p for k, p in enumerate(phases) if k == 0 or p != phases[k - 1]]
    assert order[-5:] == [
        supervisor.Phase.EXPLORE,
        supervisor.Phase.LOCALIZE,
        supervisor.Phase.TRANSIT,
        supervisor.Phase.PIVOT,
        supervisor.Phase.DONE,
    ]
    transit = [(a, st) for ph, a, st in trace if ph == supervisor.Phase.TRANSIT]
    assert [st for _, st in transit if st][0] == 1 and transit[-1][1] == 2
    start = minus - c.pivot_end_margin
    assert min(a for a, _ in transit) == pytest.approx(start, abs=1e-6)
    # PIVOT: one sweep from the pre-tilt to past the truth's other end: monotone after the
    # rate ramp, no second reversal.
    pivot = np.array([a for ph, a, _ in trace if ph == supervisor.Phase.PIVOT])
    assert pivot[0] == pytest.approx(start, abs=0.01)
    assert np.all(np.diff(pivot) >= -1e-12)
    assert len(s.pivot_limits) == 2
    assert s.pivot_limits[0] == pytest.approx(start, abs=1e-6)
    # The sweep ends once the kidney is gone past (predicted other end - tolerance).
    assert truth[0] <= s.pivot_limits[1] <= truth[0] + 0.2 * (0.05 + 0.03)
    # The whole PIVOT tilt is one pass: far less than the two-leg's out-and-back.
    assert pivot.max() - pivot.min() < (truth[0] - truth[1]) + 0.15


def test_predicted_end_extends_the_pretilt_while_the_kidney_is_seen():
    c = _cfg(
        exploration_ratio=0.02,
        localize_hold_time=0.0,
        pivot_rate=0.2,
        max_pivot_tilt=0.6,
        visibility_debounce=0.05,
        pivot_strategy="predicted_end",
        pivot_end_margin=0.02,
    )
    model = _model()  # predicted ends +-0.3576
    s, trace = _run(c, (0.5, -0.5), model)  # the real kidney is wider
    assert s.phase == supervisor.Phase.DONE, s.events
    transit = [a for ph, a, _ in trace if ph == supervisor.Phase.TRANSIT]
    # Tilted on (at pivot_rate) past the prediction until the kidney left the image.
    assert max(transit) >= 0.5
    assert s.pivot_limits[0] == pytest.approx(max(transit), abs=1e-9)
    assert s.pivot_limits[1] <= -0.5


def test_predicted_end_without_a_model_is_the_two_leg_pivot():
    c = _cfg(
        exploration_ratio=0.02,
        localize_hold_time=0.0,
        pivot_rate=0.2,
        max_pivot_tilt=0.6,
        visibility_debounce=0.05,
        pivot_strategy="predicted_end",
    )
    s, trace = _run(c, (0.3, -0.2), None)
    assert s.phase == supervisor.Phase.DONE
    assert any("no pivot model" in e[2] for e in s.events)
    assert not s.pivot_ends
    assert 0.3 <= s.pivot_limits[0] and s.pivot_limits[1] <= -0.2
