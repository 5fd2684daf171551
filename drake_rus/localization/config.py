"""Scenario section ``localization``: registration method and its parameters (seed II-F)."""

from dataclasses import dataclass, field


@dataclass
class LocalizationConfig:
    # "seed": the paper's rigid constrained plane-to-plane ICP on the mean template;
    # "deformable": pose and the template's first shape modes fitted together (MAP, the
    # statistical shape model's variances as the prior): the seed's stated future work.
    method: str = field(default="deformable", metadata={"choices": ["seed", "deformable"]})
    # Template file (absolute, or relative to the repository root).
    template: str = "models/kidney_template.npz"
    # Per-iteration clamp of each rotation-increment component (deg), eq. 19.
    theta_max_deg: float = field(default=2.0, metadata={"positive": True, "max": 45.0})
    # Stop when the mean squared projection error changes by less than this (m^2): the
    # seed's 1e-5 mm^2.
    error_change_tol: float = field(default=1e-11, metadata={"positive": True})
    max_iterations: int = field(default=200, metadata={"min": 1})
    # Also stop once an iteration's rotation (rad) and translation (m) steps fall below this
    # (1e-4: 0.006 deg and 0.1 mm, far below the localization error).
    step_tolerance: float = field(default=1e-4, metadata={"positive": True})
    # Initial translation: "centroid" (partial cloud centroid on the template origin) or
    # "zero" (the seed's t0 = 0); see drake_rus/localization/icp.py.
    init_translation: str = field(default="centroid", metadata={"choices": ["centroid", "zero"]})
    # Pairs farther apart than this are left out of each solve (m); 0 = keep all (the seed).
    max_correspondence_distance: float = field(default=0.0, metadata={"min": 0.0})
    # Deformable method: number of shape modes used (at most those in the template) and the
    # residual variance weighing data against the shape prior (m^2).
    shape_modes: int = field(default=3, metadata={"min": 0})
    shape_residual_variance: float = field(default=1e-6, metadata={"positive": True})
    # Per-iteration bound on the translation step (m): a degenerate partial view (one
    # cross-section) leaves directions unconstrained, and an unbounded least-squares step
    # along them can throw the template far away. Not in the seed (it bounds rotation only).
    max_translation_step: float = field(default=0.01, metadata={"positive": True})
    # Sanity checks of an estimate; a rejected estimate is never sent to the robot (the
    # supervisor then aborts the scan with the reason).
    min_inlier_fraction: float = field(default=0.3, metadata={"min": 0.0, "max": 1.0})
    max_rms_residual: float = field(default=0.004, metadata={"positive": True})
    max_centroid_offset: float = field(default=0.08, metadata={"positive": True})
    # Exploration shorter than this (m of probe travel) cannot localize the kidney.
    min_exploration_travel: float = field(default=0.015, metadata={"min": 0.0})
    # Partial clouds are thinned to at most this many points before registration.
    max_points: int = field(default=1500, metadata={"min": 6})
    # Adaptive exploration (beyond the seed): stop exploring once two successive estimates,
    # computed every ``adaptive_period`` s of exploration, differ by less than these.
    adaptive_exploration: bool = False
    adaptive_period: float = field(default=1.0, metadata={"positive": True})
    adaptive_translation_tol: float = field(default=0.002, metadata={"positive": True})
    adaptive_rotation_tol_deg: float = field(default=2.0, metadata={"positive": True})
    # Minimum exploration (fraction of L_m) before the adaptive stop may trigger.
    adaptive_min_ratio: float = field(default=0.3, metadata={"min": 0.0, "max": 1.0})
    # Kidney tracking after localization (localization/tracking.py, beyond the seed): the
    # frames of the last ``tracking_window`` s of TRANSIT and PIVOT are fitted to the
    # registered template every ``tracking_period`` s; an apparent kidney drift above
    # ``tracking_max_drift`` (m) on ``tracking_confirmations`` successive checks aborts the
    # scan (the pivot would image the wrong place). The 15 mm limit sits above the largest
    # apparent drift of unshifted test patients (13.4 mm on test:0, whose registration is
    # itself 9.7 mm off); a shift along the kidney's long axis is barely observable in
    # long-axis frames whose image does not reach the poles (the aperture problem), so
    # this catches gross shifts across the kidney, not every shift.
    tracking_check: bool = True
    tracking_max_drift: float = field(default=0.015, metadata={"positive": True})
    tracking_window: float = field(default=1.0, metadata={"positive": True})
    tracking_period: float = field(default=0.5, metadata={"positive": True})
    tracking_confirmations: int = field(default=2, metadata={"min": 1})
    tracking_min_frames: int = field(default=5, metadata={"min": 1})
    tracking_max_points: int = field(default=1500, metadata={"min": 10})
