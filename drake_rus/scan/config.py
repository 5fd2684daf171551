"""Scenario section ``start``: where and how the scan starts.

The seed places the probe by hand where the kidney is visible (II-E). In simulation the start
planner (:mod:`drake_rus.scan.planning`) stands in for the operator: it searches skin points
and beam directions from which the kidney lies inside the image at one of the probe's depth
presets (``imaging.depth_presets``), the beam path is clear of bone and gas, and the FR3 can
reach the pose; then the start is perturbed by a placement error, as a hand is not perfect.
SI units (m, rad) unless a name says ``_deg``.
"""

from dataclasses import dataclass, field

__all__ = ["StartConfig", "START_PLANNERS"]

START_PLANNERS = ["window", "vertical"]


@dataclass
class StartConfig:
    # "window": search the acoustic window (beam tilt, depth preset, clear path, reach);
    # "vertical": straight down over the kidney at the configured imaging.depth (the
    # seed's simulation, III-C).
    planner: str = field(default="window", metadata={"choices": START_PLANNERS})
    # Largest beam tilt from vertical searched (deg), about the body's long axis. The
    # controller's eq. 7 acts in base x-y, so strongly tilted windows fight the force loop;
    # the pivot itself tilts up to controller.max_pivot_tilt (0.6 rad, 34 deg).
    max_tilt_deg: float = field(default=30.0, metadata={"min": 0.0, "max": 60.0})
    tilt_step_deg: float = field(default=5.0, metadata={"positive": True, "max": 30.0})
    # Depth beyond the kidney's far side the image must reach (m).
    depth_margin: float = field(default=0.010, metadata={"min": 0.0, "max": 0.1})
    # Largest fraction of the fan's rays towards the kidney that may cross bone or gas.
    max_blocked_fraction: float = field(default=0.25, metadata={"min": 0.0, "max": 1.0})
    # The exploration sweep is checked for bone and gas shadows in views this far apart
    # (m): a rib crossing the sweep (ribs 11-12 pass over the kidney's upper third,
    # docs/facts/anatomy_and_ultrasound.md) shadows the kidney from the
    # segmenter, and EXPLORE ends where the kidney leaves the image.
    sweep_check_step: float = field(default=0.005, metadata={"positive": True, "max": 0.05})
    # A window is usable only if the sweep stays clear of shadows this far from its start
    # (m; the localizer needs 15 mm of kidney, localization.min_exploration_travel).
    min_clear_sweep: float = field(default=0.025, metadata={"min": 0.0, "max": 0.2})
    # Later exploration starts tried when a shadow crosses the sweep (fractions of the
    # kidney's length beyond start_fraction), like a sonographer sliding past a rib.
    max_start_shift: float = field(default=0.25, metadata={"min": 0.0, "max": 0.5})
    start_shift_step: float = field(default=0.05, metadata={"min": 0.0, "max": 0.5})
    # A later start is tried only while the sweep from it to 95% of the kidney still covers
    # this fraction of the kidney (or ER, if smaller): the paper's critical ER, 60%. A sweep
    # that reaches the far pole ends there (the kidney leaves the image), with the pole seen.
    # Before ER 0.7 the bound was ER itself, which at 0.7 left no start past 25%.
    min_sweep_fraction: float = field(default=0.6, metadata={"min": 0.0, "max": 0.95})
    # Height of the start pose above the skin along the beam (m); APPROACH lands from there.
    hover: float = field(default=0.015, metadata={"min": 0.0, "max": 0.1})
    # Where exploration starts: this fraction of the kidney's length inside its end.
    start_fraction: float = field(default=0.1, metadata={"min": 0.0, "max": 0.9})
    # The operator's placement error, drawn once per scan (seeded by random_seed and
    # placement_seed): a position offset of this size (m) in a random direction across the
    # beam, and a tilt of this angle (deg) about a random axis across the beam.
    placement_error: float = field(default=0.005, metadata={"min": 0.0, "max": 0.05})
    placement_error_angle_deg: float = field(default=3.0, metadata={"min": 0.0, "max": 20.0})
    placement_seed: int = field(default=0, metadata={"min": 0})
