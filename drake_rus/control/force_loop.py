"""The force loop along the approach axis, reduced to a linear discrete model: its closed-loop
poles and stability margin as functions of the contact stiffness (docs/force_loop.md).

The model (one degree of freedom, the tip's position x along the approach vector a, m; all
quantities are deviations from a held equilibrium):

- the force law of eq. 6 every controller period T: the contact force F is low-pass filtered
  (smoothing factor alpha per period, :func:`drake_rus.control.laws.lowpass_alpha`; 1 = no
  filter), u = -K_p3 F_f - K_d1 dF_f/dt, held in the controller's state (the command the
  station reads during the next period);
- the station's velocity driver, every plant step h: a zero-order hold of one step on the
  command, a discrete integrator x_d += h v_d, and the implicit joint PD of the arm,
  reflected to the tip: K (x_d - x) + D (v_d - v) (``robot.driver_kp``/``driver_kd``
  through the tip Jacobian, :func:`reflect_to_tip`);
- the arm and probe, an effective mass m along a (its operational-space inertia);
- the contact, SAP's linear Kelvin-Voigt law F = k (x + tau dx/dt), k the contact stiffness
  dF/dx (N/m) and tau the summed relaxation times of the two geometries (Drake's default
  0.1 s each: 0.2 s);
- the plant step as SAP integrates it: implicit (backward) Euler on the velocity, x+ = x +
  h v+, the PD and the contact both evaluated at the new state;
- the force the controller reads at step n is the contact force of the step that starts
  there (the station's unsampled ports): F_n = k (x_n + (h + tau) v+).

A stiffness of ``math.inf`` is the rigid limit: the tip does not move and F is the PD force
K x_d + D v_d (plus the momentum the step removes). The loop is stable by construction over
a stiffness range when every pole lies inside the unit circle for every k in it, including
the rigid limit; :func:`gain_margin` gives the factor by which the gains could grow before it
would not be.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from drake_rus.control.laws import lowpass_alpha

# State of the reduced model, per plant step.
STATE = ("x", "v", "x_d", "v_d", "u", "F_f", "e_prev")
_X, _V, _XD, _VD, _U, _FF, _E = range(len(STATE))

# SAP's default relaxation time of a geometry that sets none (s); a contact pair sums its two.
SAP_DEFAULT_RELAXATION_TIME = 0.1

# "Stable with margin" (docs/force_loop.md): at every contact stiffness, the rigid limit
# included, the gains could double before a pole leaves the unit circle, and no pole rings
# with a damping ratio below 0.3 (an overshoot of at most ~37 % per half period).
REQUIRED_GAIN_MARGIN = 2.0
REQUIRED_DAMPING_RATIO = 0.3

# A force counts as settled when every sample of the window lies within the desired force
# +- this band (N); the requirement on a still hold is a ripple of at most 0.1 N.
SETTLING_BAND_N = 0.1


@dataclass(frozen=True)
class AxialArm:
    """The arm and its velocity driver seen at the tip along a: effective mass (kg), PD
    stiffness (N/m) and PD damping (N s/m)."""

    mass: float
    stiffness: float
    damping: float


@dataclass(frozen=True)
class ForceLaw:
    """Eq. 6 as the controller runs it: gain K_p3 ((m/s)/N), derivative gain K_d1
    ((m/s)/(N/s)), low-pass cut-off (Hz; ``math.inf`` = no filter), period (s)."""

    gain: float
    derivative: float = 0.0
    cutoff_hz: float = math.inf
    period: float = 0.01

    @property
    def alpha(self) -> float:
        """The filter's smoothing factor per period (1 without a filter)."""
        return 1.0 if math.isinf(self.cutoff_hz) else lowpass_alpha(self.period, self.cutoff_hz)

    @classmethod
    def from_config(cls, controller) -> "ForceLaw":
        """The law a ``ControllerConfig`` runs (K_p3, K_d1, force_filter_cutoff_hz, rate_hz)."""
        return cls(
            controller.K_p3,
            controller.K_d1,
            controller.force_filter_cutoff_hz,
            1.0 / controller.rate_hz,
        )

    def scaled(self, factor: float) -> "ForceLaw":
        """The same law with both gains multiplied by ``factor``."""
        return ForceLaw(self.gain * factor, self.derivative * factor, self.cutoff_hz, self.period)


def reflect_to_tip(M, J, Kp, Kd, a, held: bool = True) -> AxialArm:
    """The arm's mass matrix ``M`` (n x n, kg m^2), joint PD gains ``Kp``, ``Kd`` (n, N m/rad
    and N m s/rad) seen at the tip along the unit approach vector ``a`` (3, in B), through
    the tip Jacobian ``J`` (6 x n, [w; v] in B).

    ``held``: the tip is held in the five other directions (a probe that sticks to the skin:
    the contact takes the lateral and rotational loads), giving the diagonal a.a entry of
    the operational-space inertia (J M^-1 J^T)^-1 and of the stiffness (J Kp^-1 J^T)^-1;
    otherwise free in them (a sliding probe): the inverse of the a.a entry of J M^-1 J^T and
    of J Kp^-1 J^T. Held is stiffer and heavier.
    """
    J = np.asarray(J, dtype=float)
    e = np.concatenate([np.zeros(3), np.asarray(a, dtype=float).reshape(3)])
    e = e / np.linalg.norm(e)

    def along(inverse_gain: np.ndarray) -> float:
        Q = J @ inverse_gain @ J.T
        return float(e @ np.linalg.solve(Q, e)) if held else 1.0 / float(e @ Q @ e)

    return AxialArm(
        mass=along(np.linalg.inv(np.asarray(M, dtype=float))),
        stiffness=along(np.diag(1.0 / np.asarray(Kp, dtype=float))),
        damping=along(np.diag(1.0 / np.asarray(Kd, dtype=float))),
    )


def plant_step(arm: AxialArm, k: float, tau: float, h: float) -> tuple[np.ndarray, np.ndarray]:
    """One plant step of the reduced model: (S, F), S the 7 x 7 map of the state
    (:data:`STATE`) with the controller's states held, F the 7-row giving the contact force
    the controller reads at the step's start (N per unit state)."""
    m, K, D = arm.mass, arm.stiffness, arm.damping
    base = m + h * D + h * h * K
    # v+ = (m v + h (K (x_d - x) + D v_d - k x)) / (base + h k (h + tau)); written with
    # r = k / den and c = k (h + tau) / den so that k = inf is the exact limit.
    if math.isinf(k):
        inv_den, r, c = 0.0, 1.0 / (h * (h + tau)), 1.0 / h
    else:
        den = base + h * k * (h + tau)
        inv_den, r, c = 1.0 / den, k / den, k * (h + tau) / den
    # v+ row (times den): [-h (K + k), m, h K, h D]; with k = inf, v+ = 0 (x stays put).
    v_row = np.zeros(len(STATE))
    v_row[[_X, _V, _XD, _VD]] = [
        -h * K * inv_den - h * r,
        m * inv_den,
        h * K * inv_den,
        h * D * inv_den,
    ]
    x_row = h * v_row
    x_row[_X] += 1.0
    # F = k x + k (h + tau) v+ = k x (base / den) + c (m v + h K (x_d - x) + h D v_d).
    F_row = np.zeros(len(STATE))
    F_row[_X] = r * base - c * h * K
    F_row[_V] = c * m
    F_row[_XD] = c * h * K
    F_row[_VD] = c * h * D
    S = np.eye(len(STATE))
    S[_X], S[_V] = x_row, v_row
    S[_XD, _VD] = h  # the integrator: x_d += h v_d (before the hold changes)
    S[_VD] = 0.0
    S[_VD, _U] = 1.0  # the hold takes the controller's command
    return S, F_row


def open_loop(
    arm: AxialArm, law: ForceLaw, k: float, tau: float, h: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The loop over one controller period cut at the command: (A, b, c) with the state map
    x+ = A x + b w when the controller's new command is an outside input w, and c the row
    giving the command the controller computes, w = c x (7 x 7, 7, 7). The controller's
    update and the plant's first step act at the period's start, simultaneously from the
    state there; the period's other plant steps follow. ``law.period`` must be a whole
    number of plant steps ``h``. The closed loop is A + b c; its loop transfer
    L(z) = c (z I - A)^-1 b (:func:`loop_transfer`)."""
    steps = law.period / h
    n = int(round(steps))
    if n < 1 or abs(steps - n) > 1e-9 * max(1.0, steps):
        raise ValueError(
            f"the controller period {law.period} s is not a whole number of plant steps {h} s"
        )
    S, F_row = plant_step(arm, k, tau, h)
    alpha, T = law.alpha, law.period
    # The controller's new states from the state at the period's start.
    F_f = alpha * F_row
    F_f[_FF] += 1.0 - alpha
    e_new = -F_f  # e = F_des - F_f (deviations)
    e_prev = np.zeros(len(STATE))
    e_prev[_E] = 1.0
    c = law.gain * e_new + law.derivative * (e_new - e_prev) / T
    first = S.copy()
    first[_U], first[_FF], first[_E] = 0.0, F_f, e_new
    b = np.zeros(len(STATE))
    b[_U] = 1.0
    A = first
    for _ in range(n - 1):
        A, b = S @ A, S @ b
    return A, b, c


def closed_loop_matrix(arm: AxialArm, law: ForceLaw, k: float, tau: float, h: float) -> np.ndarray:
    """The map of the reduced model's state over one controller period (7 x 7; see
    :func:`open_loop`)."""
    A, b, c = open_loop(arm, law, k, tau, h)
    return A + np.outer(b, c)


def loop_transfer(
    arm: AxialArm, law: ForceLaw, k: float, tau: float, h: float, frequencies_hz
) -> np.ndarray:
    """L(z) = c (z I - A)^-1 b of :func:`open_loop` at z = exp(j 2 pi f T): the closed loop's
    poles are the roots of 1 - L(z) (positive feedback: the law's sign is in c)."""
    A, b, c = open_loop(arm, law, k, tau, h)
    z = np.exp(2j * np.pi * np.asarray(frequencies_hz, dtype=float) * law.period)
    eye = np.eye(A.shape[0])
    return np.array([c @ np.linalg.solve(zi * eye - A, b) for zi in z])


def closed_loop_poles(arm: AxialArm, law: ForceLaw, k: float, tau: float, h: float) -> np.ndarray:
    """Eigenvalues of :func:`closed_loop_matrix` (per controller period), largest first,
    without the structural zeros of the states a law does not use."""
    z = np.linalg.eigvals(closed_loop_matrix(arm, law, k, tau, h))
    return z[np.argsort(-np.abs(z))]


def spectral_radius(arm: AxialArm, law: ForceLaw, k: float, tau: float, h: float) -> float:
    """Largest pole magnitude: < 1 stable; an error decays by this factor per period."""
    return float(np.abs(closed_loop_poles(arm, law, k, tau, h))[0])


def pole_frequency_hz(z: complex, period: float) -> float:
    """The frequency (Hz) a discrete pole z oscillates at, sampled every ``period`` s."""
    return abs(math.atan2(z.imag, z.real)) / (2.0 * math.pi * period)


def damping_ratio(arm: AxialArm, law: ForceLaw, k: float, tau: float, h: float) -> float:
    """The smallest damping ratio zeta of the oscillating poles (1 when none oscillates):
    z = exp(s T), zeta = -Re(s) / |s|. Negative when one grows."""
    z = closed_loop_poles(arm, law, k, tau, h)
    z = z[np.abs(z) > 1e-12].astype(complex)
    s = np.log(z) / law.period
    oscillating = np.abs(s.imag) > 1e-9
    if not oscillating.any():
        return 1.0
    s = s[oscillating]
    return float(np.min(-s.real / np.abs(s)))


def gain_margin(
    arm: AxialArm, law: ForceLaw, k: float, tau: float, h: float, upper: float = 1000.0
) -> float:
    """The factor by which both gains of ``law`` can grow before a pole leaves the unit
    circle (bisection to 0.1 %); ``upper`` when still stable there, 0 when unstable now."""

    def stable(factor: float) -> bool:
        return spectral_radius(arm, law.scaled(factor), k, tau, h) < 1.0

    if not stable(1.0):
        return 0.0
    if stable(upper):
        return upper
    lo, hi = 1.0, upper
    while hi / lo > 1.001:
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if stable(mid) else (lo, mid)
    return lo


def stiffness_sweep(arm: AxialArm, law: ForceLaw, stiffnesses, tau: float, h: float) -> list:
    """Rows (k N/m, spectral radius, frequency Hz of the largest pole, gain margin) over
    ``stiffnesses`` (``math.inf`` allowed)."""
    rows = []
    for k in stiffnesses:
        z = closed_loop_poles(arm, law, k, tau, h)[0]
        rows.append(
            (
                float(k),
                float(abs(z)),
                pole_frequency_hz(z, law.period),
                gain_margin(arm, law, k, tau, h),
            )
        )
    return rows


def stiffness_at_force(indentations, forces, force: float) -> float:
    """dF/dx (N/m) at ``force`` (N) of a measured force-indentation curve (m, N; increasing
    indentation): the slope of the two samples around it."""
    x = np.asarray(indentations, dtype=float)
    F = np.asarray(forces, dtype=float)
    if x.shape != F.shape or x.size < 2:
        raise ValueError(
            "indentations and forces: expected two equal-length arrays of at "
            f"least 2 samples, got shapes {x.shape} and {F.shape}"
        )
    if not (np.all(np.diff(x) > 0) and np.all(np.diff(F) > 0)):
        raise ValueError("indentations and forces: expected both increasing")
    if not F[0] <= force <= F[-1]:
        raise ValueError(f"force: {force} N is outside the measured {F[0]:.3g}-{F[-1]:.3g} N")
    i = int(np.clip(np.searchsorted(F, force), 1, F.size - 1))
    return float((F[i] - F[i - 1]) / (x[i] - x[i - 1]))


def force_statistics(
    times, forces, desired: float, window: float, band: float = SETTLING_BAND_N
) -> dict:
    """The contact force over the last ``window`` s of a log (s, N): ``mean_n``,
    ``ripple_n`` (the RMS about the mean, i.e. the standard deviation, the same definition
    as the scan's force statistics), ``peak_to_peak_n``, ``max_error_n`` (largest
    |F - desired|) and ``settled``: every sample within ``desired`` +- ``band``. With no
    sample in the window the values are None and ``settled`` is False. The log must sample
    the force at least at the controller's rate, or an oscillation aliases away."""
    t = np.asarray(times, dtype=float)
    F = np.asarray(forces, dtype=float)
    out = {
        "window_s": float(window),
        "mean_n": None,
        "ripple_n": None,
        "peak_to_peak_n": None,
        "max_error_n": None,
        "settled": False,
    }
    if t.size == 0:
        return out
    sel = t >= t[-1] - window
    F = F[sel]
    error = float(np.max(np.abs(F - desired)))
    out.update(
        mean_n=float(F.mean()),
        ripple_n=float(F.std()),
        peak_to_peak_n=float(np.ptp(F)),
        max_error_n=error,
        settled=bool(error <= band),
    )
    return out


def step_response_metrics(
    times,
    forces,
    errors_deg,
    desired: float,
    step_at: float,
    band: float = 0.5,
    tolerance_deg: float = 1.0,
    touch_n: float = 0.5,
) -> dict:
    """The step responses of one log (s, N, deg; notebooks/controller_tuning.ipynb): the force
    step from the start (the probe lands and presses towards ``desired``) until ``step_at``,
    then a step of the approach vector there.

    ``touch_s``: the first sample above ``touch_n``; ``force_settling_s``: from the touch to
    the last sample before ``step_at`` outside ``desired`` +- ``band`` (0 if none is);
    ``force_final_n``: the force at the orientation step; ``tilt_below_1deg_s``: from
    ``step_at`` to the first sample with an approach error below ``tolerance_deg``;
    ``tilt_final_deg``: the last error. A response that does not happen within the log is
    None: no touch, a force still outside the band at the step (not settled), an error never
    below the tolerance; never a time of 0 s."""
    t = np.asarray(times, dtype=float)
    F = np.asarray(forces, dtype=float)
    err = np.asarray(errors_deg, dtype=float)
    before, after = t < step_at, t >= step_at
    touched = np.nonzero(before & (F > touch_n))[0]
    touch = float(t[touched[0]]) if touched.size else None
    settle = None
    if touch is not None:
        outside = np.nonzero(before & (t >= touch) & ~(np.abs(F - desired) <= band))[0]
        last = np.nonzero(before)[0][-1]
        if not outside.size:
            settle = 0.0
        elif outside[-1] != last:
            settle = float(t[outside[-1]] - touch)
    below = np.nonzero(after & (err < tolerance_deg))[0]
    return {
        "touch_s": touch,
        "force_settling_s": settle,
        "force_final_n": float(F[after][0]) if after.any() else None,
        "tilt_below_1deg_s": float(t[below[0]] - step_at) if below.size else None,
        "tilt_final_deg": float(err[-1]) if err.size else None,
    }


def phase_force_statistics(
    times, forces, phases, names=("EXPLORE", "LOCALIZE", "PIVOT"), settle: float = 0.5
) -> dict:
    """Mean and ripple (RMS about the mean, N) of the force in each of ``phases`` ((name,
    start s, end s) rows) named in ``names``: {name: {"mean_n", "ripple_n"}}; EXPLORE skips
    its first ``settle`` s (the landing), as the scan's force statistics do. A phase that
    did not occur, or has no sample, is left out."""
    t = np.asarray(times, dtype=float)
    F = np.asarray(forces, dtype=float)
    out = {}
    for name, start, end in phases:
        if name not in names:
            continue
        skip = settle if name == "EXPLORE" else 0.0
        sel = (t >= start + skip) & (t <= end)
        if sel.any():
            out[name] = {"mean_n": float(F[sel].mean()), "ripple_n": float(F[sel].std())}
    return out
