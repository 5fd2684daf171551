"""Scenario sections ``controller`` and ``safety``.

Gain names follow the seed paper (section II-C, eq. 1-12; II-E, eq. 17; II-G, eq. 23). Units
are SI; a gain's unit is written next to it. Limits quote ``docs/facts/fr3.md`` (FR3 specification
2025): joint velocity limits (rectangular set) dq = [2, 1, 1.5, 1.25, 3, 1.5, 3] rad/s,
Cartesian limits 3.0 m/s translation and 2.5 rad/s rotation. Our defaults sit well below them
because the probe touches a person.
"""

from dataclasses import dataclass, field

from drake_rus.config_schema import physical

# docs/facts/fr3.md, "Limits": conservative rectangular joint velocity set (rad/s).
FR3_DQ_RECTANGULAR = [2.0, 1.0, 1.5, 1.25, 3.0, 1.5, 3.0]


@dataclass
class ControllerConfig:
    # Controller update rate (Hz); the plant runs at 1 kHz, images at 20 Hz.
    rate_hz: float = field(
        default=100.0,
        metadata=physical(
            10.0, 1000.0, "Hz", "the controller runs at most at the FR3's 1 kHz", positive=True
        ),
    )
    # Desired contact force along the approach vector (N); the seed used 9 N in vivo.
    desired_force: float = field(
        default=9.0, metadata=physical(0.0, 30.0, "N", "probe contact forces are a few N to 20 N")
    )

    # --- Orientation alignment (eq. 1-5) ---
    # K_p1 (1/s): approach-vector alignment gain, omega_a = K_p1 (a x a_des) + ... (eq. 2).
    K_p1: float = field(default=3.0, metadata={"min": 0.0})
    # K_p11 (-): feed-forward gain on a_des rate, K_p11 (a x da_des/dt) (eq. 2); 1 = exact.
    K_p11: float = field(default=1.0, metadata={"min": 0.0})
    # K_p2 (1/s): orientation-vector alignment gain about a (eq. 4).
    K_p2: float = field(default=3.0, metadata={"min": 0.0})

    # --- Force PD (eq. 6) ---
    # The three gains below are chosen with the reduced model of the force loop
    # (drake_rus.control.force_loop, docs/force_loop.md): at the 10 ms and the 1 ms plant
    # step, for every contact stiffness up to the rigid limit (a probe stuck to the skin
    # makes the contact look far stiffer than the tissue) and every arm pose of the scans
    # of test:0-2, the gains could double before the loop goes unstable and no pole rings
    # with a damping ratio below 0.3 (worst case 2.8 and 0.30). The earlier 0.006 / 5e-5 /
    # 5 Hz oscillated at 50 Hz at the 1 ms step once the probe stuck (issue 32). The price
    # is a slower loop: on test:0 the true force's RMS about its mean in EXPLORE went from
    # 0.06 to 0.10 N, in PIVOT from 0.09 to 0.15 N (E_trans, V unchanged).
    # K_p3 ((m/s)/N): proportional force gain, v_z = K_p3 (F_des - F_z) a.
    K_p3: float = field(default=0.004, metadata={"min": 0.0})
    # K_d1 ((m/s)/(N/s)): derivative gain on the low-pass filtered force error. Kept small:
    # the derivative acts at the controller's Nyquist rate, where the force responds to the
    # command at once through the driver's damping.
    K_d1: float = field(default=0.00001, metadata={"min": 0.0})
    # Cut-off (Hz) of the first-order low-pass on the estimated contact force.
    force_filter_cutoff_hz: float = field(default=1.25, metadata={"positive": True})

    # --- Position P (eq. 7) ---
    # K_p4, K_p5 (1/s): tip x / y tracking gains in the base frame.
    K_p4: float = field(default=2.0, metadata={"min": 0.0})
    K_p5: float = field(default=2.0, metadata={"min": 0.0})

    # --- Null-space differential IK (eq. 10-12) ---
    # K_p6 (rad/s per unit manipulability gradient): null-space manipulability ascent (eq. 11).
    K_p6: float = field(default=2.0, metadata={"min": 0.0})
    # The null-space velocity K_p6 grad m(q) is refreshed at this period (s): a slow
    # secondary task; each refresh costs eight Jacobians.
    null_space_period: float = field(default=0.02, metadata={"positive": True})
    # Finite-difference step epsilon (rad) of the manipulability gradient (eq. 12).
    manipulability_epsilon: float = field(default=1e-4, metadata={"positive": True})
    # Singularity damping: below this smallest singular value of J the pseudo-inverse is
    # damped (Nakamura/Chiaverini variable damping), with at most singular_damping_max.
    singular_value_threshold: float = field(default=0.03, metadata={"positive": True})
    singular_damping_max: float = field(default=0.03, metadata={"min": 0.0})
    # Joint velocity limits (rad/s) of the command: half the FR3 rectangular set
    # (docs/facts/fr3.md).
    joint_velocity_limits: list[float] = field(
        default_factory=lambda: [0.5 * v for v in FR3_DQ_RECTANGULAR],
        metadata={"length": 7, "positive": True},
    )
    # Within this distance (rad) of a joint limit the velocity towards it ramps down to zero.
    joint_limit_margin: float = field(default=0.1, metadata={"positive": True})
    # Twist saturation: tip speed (m/s; FR3 limit 3.0) and angular speed (rad/s; FR3 2.5).
    max_tip_speed: float = field(default=0.05, metadata={"positive": True, "max": 3.0})
    max_angular_speed: float = field(default=0.6, metadata={"positive": True, "max": 2.5})

    # --- Scan (section II-E, II-G) ---
    # Exploration scan speed v_scan (m/s) along the base y-axis (seed: 5 mm/s, eq. 17).
    scan_speed: float = field(default=0.005, metadata={"positive": True, "max": 0.05})
    # Probe orientation during APPROACH and EXPLORE: "hold" keeps the start orientation (the
    # seed's manual placement); "transverse" turns the array o onto the base x-axis (across
    # the patient, a transverse image) about the current approach vector.
    explore_orientation: str = field(
        default="transverse", metadata={"choices": ["hold", "transverse"]}
    )
    # Where APPROACH lands the probe: tip (x, y) in the base frame (m); empty = straight down
    # from the start pose. The seed places the probe by hand where the kidney is visible.
    start_xy: list[float] = field(default_factory=list)
    # Scan direction along the base y-axis (the patient lies along y).
    scan_direction: str = field(default="-y", metadata={"choices": ["+y", "-y"]})
    # K_p7 (m/s per unit of normalised centroid offset): mask-centring gain (eq. 17).
    K_p7: float = field(default=0.1, metadata={"min": 0.0})
    # Exploration ratio ER in [0, 1] and reference kidney length L_m (m): EXPLORE ends after
    # ER * L_m of travel (section III-C). 0.7, not the seed's critical 0.6: its rule gives
    # 80-90% on our pipeline, and 0.7 halves the default scan's mean E_trans on test:0-7
    # (3.3 -> 1.7 mm) and on the Visible Human female (5.0 -> 2.0 mm; her 136 mm left
    # kidney, which the partial cloud's length estimate underestimates, 13.3 -> 5.1 mm) for
    # about 2 s more exploration (docs/results/exploration_ratio.md). 0.6 is the paper's.
    exploration_ratio: float = field(default=0.7, metadata={"min": 0.0, "max": 1.0})
    kidney_length: float = field(default=0.10, metadata={"positive": True})
    # L of the exploration: "fixed" (L_m above, the seed) or "estimated" (beyond the seed):
    # the patient's kidney length, estimated by the localizer from the cloud explored so far
    # (its ``kidney_length_estimate``; L_m until it exists), clipped to
    # [L_m / exploration_length_factor, exploration_length_factor x L_m] so the travel
    # never exceeds that factor times ER L_m. Real kidneys are 88-140 mm long. Measured on
    # the 15 test patients (kinematic, ER 0.6, oracle masks): mean E_trans 4.17 -> 3.69 mm
    # (deformable) and 4.61 -> 4.35 mm (seed), at most 1.1 mm worse on one patient, travel
    # 56-78 mm instead of 60 mm (mean 64.6 mm); the VH female's 136 mm left kidney 20.0 ->
    # 14.8 mm.
    exploration_length: str = field(
        default="estimated", metadata={"choices": ["fixed", "estimated"]}
    )
    exploration_length_factor: float = field(default=1.5, metadata={"min": 1.0, "max": 3.0})
    # Contact is "made" when the filtered force reaches this fraction of desired_force.
    contact_fraction: float = field(default=0.8, metadata={"positive": True, "max": 1.0})
    # ... and has stayed there this long (s): a transient (an accelerating arm's torque
    # estimate, a knock) is not contact; tissue holds the force.
    contact_dwell: float = field(default=0.2, metadata={"min": 0.0, "max": 2.0})
    # APPROACH gives up (ABORT "no contact") after the tip has moved this far along the
    # approach vector from where it started (m), or after approach_timeout (s): the probe
    # is placed a few cm above the skin (the start planner hovers 15 mm above it).
    approach_max_travel: float = field(default=0.06, metadata={"positive": True, "max": 0.3})
    approach_timeout: float = field(default=20.0, metadata={"positive": True})
    # The kidney counts as having left the image after this long invisible (s).
    visibility_debounce: float = field(default=0.15, metadata={"min": 0.0})
    # EXPLORE ends when the kidney leaves the image only once it has been seen over this
    # much of the sweep (m; localization.min_exploration_travel): a kidney seen over less
    # cannot be localized (the scan would ABORT), so the sighting is forgotten and the sweep
    # goes on. A breath that carries the kidney out of a plane near its pole as a hold
    # begins left it in view for 0.8 mm (test:2, the breath-hold protocol: ABORT).
    explore_min_seen_travel: float = field(default=0.015, metadata={"min": 0.0})
    # The probe must follow the sweep: its tip may lie more than explore_follow_bound (m:
    # explore_follow_limit, or EXPLORE_LAG_TIME x scan_speed if larger) from the sweep's
    # x-y set-point for at most explore_follow_time (s), else ABORT. A normal sweep lags
    # by about 0.7 s of travel (3.4 mm at most at 5 mm/s: test:0, KiTS19 case 1); a wrist
    # at its limit holds the whole arm still (the differential IK scales every joint's
    # velocity into its bounds), and the sweep's travel would go on counting without the
    # probe moving (KiTS19 case 12, left kidney, before the re-exploration's turn went
    # back the wrist's way: 55 s still, then "seen over 0 mm").
    explore_follow_limit: float = field(default=0.015, metadata={"positive": True, "max": 1.0})
    explore_follow_time: float = field(default=2.0, metadata={"positive": True, "max": 30.0})
    # LOCALIZE holds the probe at least this long (s) before reading the kidney pose.
    localize_hold_time: float = field(default=0.5, metadata={"min": 0.0})
    # LOCALIZE aborts if the localizer has no pose ready after this time (s).
    localize_timeout: float = field(default=30.0, metadata={"positive": True})
    # TRANSIT ends within this tip distance (m) of p* and approach error (rad) of r3*.
    transit_position_tolerance: float = field(default=0.002, metadata={"positive": True})
    transit_angle_tolerance: float = field(default=0.02, metadata={"positive": True})
    # TRANSIT aborts if p* is not reached in this time (s).
    transit_timeout: float = field(default=30.0, metadata={"positive": True})
    # Pivot angular rate theta_dot (rad/s) (eq. 23) and maximum tilt from r3* (rad).
    pivot_rate: float = field(default=0.1, metadata={"positive": True, "max": 1.0})
    max_pivot_tilt: float = field(default=0.6, metadata={"positive": True, "max": 1.2})
    # At the tilt cap with the kidney still in the image (a wide or shallow kidney needs more
    # tilt on one side than max_pivot_tilt allows; fresh decubitus patients at the 100 mm
    # preset need up to 45 deg), the tip slides on the skin, tilt held, across the array
    # towards the side the probe leans to (the image plane moves on past the cap's plane,
    # as a sonographer slides the probe) at scan_speed until the kidney has left the image
    # and the slide has passed the one the registered template predicts (the segmenter
    # misses a pole's last small sections), at most that slide plus cap_slide_margin and
    # at most cap_slide_max (m); after the first leg it slides back to p* before the second.
    # 0: no slide (the leg ends at the cap, the scan's verdict then INCOMPLETE).
    cap_slide_max: float = field(default=0.03, metadata={"min": 0.0, "max": 0.1})
    # Beyond the template's predicted slide (m): the template (one length for every
    # kidney) misplaces a kidney's edge by up to ~10 mm (the pole offsets, scan/verdict.py).
    cap_slide_margin: float = field(default=0.01, metadata={"min": 0.0, "max": 0.1})
    # The probe must follow the pivot: its axis may lag the commanded a_des by more than
    # pivot_follow_limit (rad) for at most pivot_follow_time (s), else ABORT (a joint held
    # at its limit would otherwise let the sweep "finish" without imaging). A normal pivot
    # lags by 0.2 deg at most (test:0, test:3 supine, test:1 decubitus).
    pivot_follow_limit: float = field(default=0.05, metadata={"positive": True, "max": 3.2})
    pivot_follow_time: float = field(default=0.5, metadata={"positive": True, "max": 5.0})
    # The tilt rate ramps at this angular acceleration (rad/s^2), so reversals are smooth.
    pivot_acceleration: float = field(default=0.4, metadata={"positive": True})
    # Pivot strategy: "two_leg" (the seed: one way until the kidney leaves, back through
    # the start to the other side) or "predicted_end" (beyond the seed): at the end of
    # TRANSIT the probe tilts, without imaging the sweep, to the end the registered template
    # predicts on one side plus pivot_end_margin (further, at pivot_rate, while the kidney is
    # still in the image), then PIVOT sweeps once to the other side, ended by the kidney
    # leaving the image past the predicted other end (less pivot_end_tolerance) or the
    # maximum tilt. Needs the ScanSupervisor's pivot_model input (template and fan);
    # without it the pivot is two_leg.
    pivot_strategy: str = field(
        default="two_leg", metadata={"choices": ["two_leg", "predicted_end"]}
    )
    # Tilt (rad) beyond the predicted end where the pre-tilt stops. The prediction is
    # already conservative (a template point within half the elevational width of the plane
    # counts as imaged) and the pre-tilt tilts on while the kidney is seen, so no margin is
    # needed: closed loop on test:0-4, 0.05 rad gave 23.5% less whole-pivot eps than
    # two_leg, 0 gave 30.1%, both at V 0.983.
    pivot_end_margin: float = field(default=0.0, metadata={"min": 0.0, "max": 0.5})
    # On the single sweep, a loss of the kidney ends it only this close (rad) to the
    # predicted other end or beyond (the prediction's error on test patients: 0.1-4.7 deg).
    pivot_end_tolerance: float = field(default=0.1, metadata={"min": 0.0, "max": 1.2})
    # The "segmentation lost" stop in PIVOT tells an expected absence from a loss with the
    # registered template's predicted section in the image (supervisor.absence_expected):
    # where the template puts the kidney out of view (past a pivot end) its absence is
    # expected; after a leg's end it stays expected until the kidney is seen again or the
    # template's section is back to this share of its section at the pivot's start (the
    # probe has turned back over the kidney). Not 0: the template (108 mm) overhangs the
    # pole of a kidney 20-30 mm shorter where the leg ended, and the return leg spends up
    # to 0.8 s decelerating, reversing and coming back to that pole; not 1: a loss near the
    # start would never count.
    reacquire_share: float = field(default=0.5, metadata={"positive": True, "max": 1.0})
    # Tilt rate (rad/s) of the pre-tilt to the predicted end (no images needed).
    pretilt_rate: float = field(default=0.25, metadata={"positive": True, "max": 1.0})
    # The pivot pose: [] (the seed) T* of the registered kidney pose (eq. 20-22), after
    # EXPLORE and LOCALIZE; or a given pose [x (m), y (m), yaw (rad)]: the tip over (x, y)
    # in the base frame, the array (r1) at angle yaw from the base x-axis about the base
    # z-axis, the probe pointing straight down (r3 = [0, 0, -1], as in eq. 20-22), e.g. an
    # operator's placement (the seed's in-vivo GT-OP and NOP were placed by a sonographer,
    # III-G). With a given pose the scan skips EXPLORE and LOCALIZE: APPROACH lands,
    # TRANSIT slides and turns to the pose, PIVOT (two_leg) sweeps; summary.json says which
    # pose the pivot used. Not with pivot_strategy predicted_end (it predicts from the
    # registered pose) nor with sweep line.
    pivot_pose: list[float] = field(default_factory=list)
    # What the scan sweeps: "pivot" (the seed: explore, localize, pivot, II-E..G) or "line"
    # (the seed's straight-line baseline SL, III-E: "equivalent to setting ER = 100% at
    # exploration"): the exploration controller (eq. 17) from wherever APPROACH lands
    # (e.g. start_xy beyond the kidney's end: before the kidney is first seen its absence
    # neither ends the sweep nor trips the segmentation watchdog) until the kidney has left
    # the image (visibility_debounce), then DONE; no localization, no pivot. The sweep's
    # costs (eps, n, V) are then those of the EXPLORE frames.
    sweep: str = field(default="pivot", metadata={"choices": ["pivot", "line"]})
    # The line sweep's longest travel (m) along the scan direction: there it ends, DONE if
    # the kidney was seen, ABORT if it never came into view.
    line_sweep_max_travel: float = field(default=0.2, metadata={"positive": True, "max": 0.5})
    # When the kidney tracking says the kidney moved during TRANSIT or PIVOT (a patient
    # shift): re-localize (backing out of the kidney, a new exploration into it and a new
    # registration) at most this many times, then ABORT; 0: ABORT at once.
    max_relocalizations: int = field(default=2, metadata={"min": 0, "max": 10})
    # A sonographer's second look: at the pivot's end, before DONE, the scan compares the
    # pivot's view of the kidney with the registration (the rule the verdict's
    # pivot_residual check applies afterwards, localization.pivot_view); when it
    # contradicts the fit and a re-localization is still allowed (max_relocalizations),
    # the scan backs out, sweeps the whole kidney (until it leaves the image, at most
    # exploration_length_factor x kidney_length past where it came into view: a full
    # cloud leaves the registration no wrong minimum, docs/results/real_kidneys.md),
    # registers and pivots again; once per scan. False: DONE at the pivot's end, the
    # verdict alone judging the pivot's view.
    second_look: bool = True


@dataclass
class SafetyConfig:
    # Contact force ceiling (N): passive force limiters sit around 20 N (facts).
    force_ceiling: float = field(
        default=20.0,
        metadata=physical(1.0, 50.0, "N", "passive force limiters sit around 20 N", positive=True),
    )
    # After a force-ceiling stop, retract along -a by this distance (m) at this speed (m/s);
    # 0 disables the retract (a plain stop).
    retract_distance: float = field(default=0.01, metadata={"min": 0.0, "max": 0.05})
    retract_speed: float = field(default=0.02, metadata={"positive": True, "max": 0.1})
    # Measured tip speed (m/s) above which the robot is stopped (FR3 Cartesian limit 3.0 m/s).
    max_tip_speed: float = field(default=0.15, metadata={"positive": True, "max": 3.0})
    # Command clamp: commanded tip speed (m/s) is scaled down to this.
    command_tip_speed: float = field(default=0.08, metadata={"positive": True, "max": 3.0})
    # Joint velocity limits (rad/s) of the command (the FR3 rectangular set, docs/facts/fr3.md):
    # commands are scaled into them; a measured velocity beyond them stops the robot.
    joint_velocity_limits: list[float] = field(
        default_factory=lambda: list(FR3_DQ_RECTANGULAR), metadata={"length": 7, "positive": True}
    )
    # Workspace box of the probe tip in the base frame (m): [x, y, z] min and max.
    workspace_min: list[float] = field(
        default_factory=lambda: [0.2, -0.5, -0.05], metadata={"length": 3}
    )
    workspace_max: list[float] = field(
        default_factory=lambda: [0.9, 0.5, 0.7], metadata={"length": 3}
    )
    # Watchdogs (s): newest image older than this; robot state unchanged this long while
    # motion is commanded; kidney invisible this long while the supervisor needs it.
    image_timeout: float = field(default=0.25, metadata={"positive": True})
    state_timeout: float = field(default=0.05, metadata={"positive": True})
    segmentation_timeout: float = field(default=1.0, metadata={"positive": True})
    # A live (hardware) run that falls this far (s) behind the wall clock is stopped at zero
    # velocity: its commands would reach the robot late.
    realtime_lag: float = field(default=0.25, metadata={"positive": True, "max": 2.0})


RESPIRATION_MODES = ["none", "breath_hold", "gated"]


@dataclass
class RespirationConfig:
    """Scenario section ``respiration``: how the scan copes with a breathing patient, from
    what any station has (drake_rus/control/respiration.py; docs/reliability.md).

    ``mode``: "none" (the seed's simulation: a still kidney is assumed); "breath_hold" (the
    seed's in-vivo protocol, III-B: before EXPLORE and before TRANSIT/PIVOT the scan asks
    for a breath-hold and moves only while one is sensed, at most ``hold_limit`` s each, the
    patient breathing freely in between and during LOCALIZE); "gated" (free breathing: the
    probe moves and the exploration cloud takes frames only in the end-expiration windows
    the estimator finds). SI units."""

    mode: str = field(default="none", metadata={"choices": RESPIRATION_MODES})
    # --- the breath-hold protocol ---
    # Longest hold asked for (s), counted from the sensed onset: a phase that needs longer
    # is split into several holds, the probe held still under force control between them.
    hold_limit: float = field(
        default=15.0,
        metadata=physical(
            3.0,
            40.0,
            "s",
            "the seed kept each breath-hold step under 20 s; lung cancer patients hold a "
            "deep inspiration for a median 21 s (Tibdewal 2015)",
        ),
    )
    # Free breathing between two holds (s), and before the first one: the estimator learns
    # the patient's breathing from it.
    recovery_time: float = field(default=8.0, metadata={"min": 0.0, "max": 60.0})
    # The hold is asked again if none is sensed this long (s) after the prompt; the scan
    # aborts after max_prompts unanswered prompts in a row.
    hold_wait: float = field(default=8.0, metadata={"positive": True})
    max_prompts: int = field(default=4, metadata={"min": 1})
    # "in" (breathe in and hold: the seed's) or "out" (breathe out and hold).
    hold_level: str = field(default="in", metadata={"choices": ["in", "out"]})
    # Speak the prompts with a speech synthesiser (espeak-ng or espeak) when one is
    # installed; the console line is always printed.
    speak: bool = True
    # --- the respiration-phase estimator ---
    # The wall's level is the tip's height plus the indentation F / contact_stiffness.
    contact_stiffness: float = field(
        default=1500.0,
        metadata=physical(
            300.0,
            1.0e5,
            "N/m",
            "the probe's normal contact stiffness on the simulated bodies is 441-4928 N/m "
            "(docs/force_loop.md)",
        ),
    )
    # The wall's speed is fitted over this window (s); it is "still" below still_speed.
    speed_window: float = field(default=0.25, metadata={"positive": True, "max": 2.0})
    still_speed: float = field(default=0.0006, metadata={"positive": True, "max": 0.01})
    # Stillness this long (s) above the end-expiration band is a hold; stillness at any
    # level for still_long s is one too (a hold at end-expiration, or no visible breathing).
    hold_confirm: float = field(default=0.25, metadata={"min": 0.0, "max": 5.0})
    still_long: float = field(default=3.0, metadata={"positive": True, "max": 30.0})
    # The recent breathing (s) the end-expiration level and the tidal range are taken from.
    history: float = field(default=10.0, metadata={"positive": True, "max": 60.0})
    # End-expiration: within this fraction of the tidal range above its level, and still.
    end_expiration_band: float = field(default=0.3, metadata={"min": 0.0, "max": 1.0})
