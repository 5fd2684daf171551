"""Respiration from what any station senses, the breath-hold protocol and gating
(drake_rus.control.respiration), on signals made with the patient's breathing model
(drake_rus.anatomy.motion)."""

import dataclasses
import math

import numpy as np
import pytest

from drake_rus.anatomy import motion as M
from drake_rus.control import respiration as R
from drake_rus.control.config import RespirationConfig
from drake_rus.control.respiration_systems import BreathPrompter, speech_command

DT = 0.01
A_DOWN = np.array([0.0, 0.0, -1.0])


def breathe(
    cfg,
    prompts,
    t_end,
    *,
    wall=0.004,
    slope=0.0,
    speed=0.0,
    moving=None,
    seed=1,
    turn=None,
    own=None,
    mode="breath_hold",
):
    """Feeds the estimator a probe pressing on a wall that rises ``wall`` m per unit of
    the patient's respiratory level, sliding at ``speed`` m/s along y over skin of
    ``slope`` while ``moving(t)``; ``turn(t)`` (m) adds what the probe's own tilts and turns
    do to the wall's reading, ``own(t)`` (m/s) is the speed the scan commands (unknown if
    None). Returns (times, true holds, estimator state)."""
    rcfg = RespirationConfig(mode=mode)
    s_b = M.breath_start(cfg, seed)
    s_r = R.RespirationState()
    y, holds, prompts = 0.0, [], sorted(prompts)
    rng = np.random.default_rng(0)
    times = np.arange(0.0, t_end, DT)
    for t in times:
        while prompts and prompts[0][0] <= t:
            s_b = M.breath_prompted(s_b, prompts.pop(0)[1], t, cfg)
        s_b = M.breath_advance(s_b, t, cfg, seed)
        holds.append(M.breath_holding(s_b))
        if moving is not None and moving(t):
            y += speed * DT
        z = 0.2 + wall * M.breath_level(s_b, t, cfg) + slope * y + rng.normal(0, 2e-5)
        z += turn(t) if turn is not None else 0.0
        speed_cmd = own(t) if own is not None else math.nan
        s_r = R.respiration_update(
            s_r, t, np.array([0.5, y, z]), A_DOWN, 9.0, True, rcfg, speed_cmd
        )
    return times, np.array(holds), s_r


def true_hold_edges(times, holds):
    edges = np.diff(holds.astype(int))
    return times[1:][edges == 1], times[1:][edges == -1]


def test_wall_level_adds_the_indentation_along_the_beam():
    assert R.wall_level([0, 0, 0.2], A_DOWN, 9.0, 1500.0) == pytest.approx(0.206)
    tilted = np.array([0.0, math.sin(0.3), -math.cos(0.3)])
    assert R.wall_level([0, 0, 0.2], tilted, 9.0, 1500.0) == pytest.approx(
        0.2 + 0.006 * math.cos(0.3)
    )


def test_breathing_model_pattern_and_prompted_holds():
    """Lujan's cos^2n breath with breath-to-breath variability, and a hold when told:
    reached after the reaction time and an inspiration, drifting cranially, released when
    told (then breathing again from end-expiration)."""
    cfg = M.BreathingConfig(enabled=True, amplitude=0.015, rate_per_min=15.0)
    program = M.BreathingProgram(cfg, 3)
    t = np.arange(0.0, 120.0, DT)
    u = np.array([program.level(x) for x in t])
    assert abs(u.mean() - 0.375) < 0.1  # sin^4 averages 3/8 of a breath's depth
    assert np.mean(u < 0.1) > 0.3  # a long dwell at end-expiration
    assert np.max(np.abs(np.diff(u))) < 0.05  # continuous
    peaks = np.nonzero((u[1:-1] > u[:-2]) & (u[1:-1] >= u[2:]) & (u[1:-1] > 0.3))[0]
    periods = np.diff(t[1:-1][peaks])
    assert 3.3 < periods.mean() < 4.7 and periods.std() > 0.2  # 15/min, varying
    assert np.std(u[1:-1][peaks]) > 0.1  # the depth varies too
    times, holds, _ = breathe(cfg, [(10.0, M.Prompt.HOLD_IN), (25.0, M.Prompt.BREATHE)], 40.0)
    on, off = true_hold_edges(times, holds)
    assert len(on) == 1 and 10.5 < on[0] < 13.0  # reaction 0.5 s, then the breath in
    assert off[0] == pytest.approx(25.5, abs=0.02)  # told, reacted
    s = M.breath_start(cfg, 1)
    s = M.breath_prompted(s, M.Prompt.HOLD_IN, 0.0, cfg)
    s = M.breath_advance(s, 5.0, cfg, 1)
    assert M.breath_holding(s)
    u5, u15 = M.breath_level(s, 5.0, cfg), M.breath_level(s, 15.0, cfg)
    drift = (u5 - u15) * cfg.amplitude / 10.0  # cranial, m/s
    assert 0.5 * cfg.hold_drift <= drift <= 1.5 * cfg.hold_drift
    # Nobody says breathe: the patient lets go by themselves (max_hold, drawn 0.75-1.25 x).
    s = M.breath_advance(s, 40.0, cfg, 1)
    assert not M.breath_holding(s)


def test_estimator_finds_holds_within_0_3_s_and_decides_soon_after():
    cfg = M.BreathingConfig(enabled=True, amplitude=0.015, rate_per_min=15.0)
    prompts = [(12.0, M.Prompt.HOLD_IN), (24.0, M.Prompt.BREATHE)]
    prompts += [(34.0, M.Prompt.HOLD_IN), (44.0, M.Prompt.BREATHE)]
    times, holds, s = breathe(cfg, prompts, 52.0)
    on, off = true_hold_edges(times, holds)
    assert len(on) == 2 and len(off) == 2
    est_on = [(w, d) for w, d, a, b in s.transitions if b == R.HOLDING]
    est_off = [(w, d) for w, d, a, b in s.transitions if a == R.HOLDING]
    assert len(est_on) == 2 and len(est_off) == 2, s.transitions
    for truth, (when, decided) in zip(list(on) + list(off), est_on + est_off):
        assert abs(when - truth) <= 0.3
        assert decided - truth <= 0.6
    # Breathing between the holds: end-expiration windows, each within a true dwell.
    ee = [w for w, d, a, b in s.transitions if b == R.END_EXPIRATION]
    assert len(ee) >= 3


def test_a_hold_stays_a_hold_while_the_probe_slides_over_sloping_skin():
    """EXPLORE in a hold: the probe slides 5 mm/s over skin rising 0.15 m/m (0.75 mm/s of
    wall motion that is not breathing): the hold is not lost; its end is still found."""
    cfg = M.BreathingConfig(enabled=True, amplitude=0.015, rate_per_min=15.0)
    prompts = [(12.0, M.Prompt.HOLD_IN), (26.0, M.Prompt.BREATHE)]
    times, holds, s = breathe(
        cfg, prompts, 32.0, slope=0.15, speed=0.005, moving=lambda t: 15.0 <= t <= 25.0
    )
    on, off = true_hold_edges(times, holds)
    changes = [(w, a, b) for w, d, a, b in s.transitions if on[0] - 1 < w < off[0] + 1]
    into = [w for w, a, b in changes if b == R.HOLDING]
    out_of = [w for w, a, b in changes if a == R.HOLDING]
    assert len(into) == 1 and len(out_of) == 1, changes
    assert abs(out_of[0] - off[0]) <= 0.3


def test_a_hold_end_after_the_slide_stopped_is_dated_by_a_change_point():
    """EXPLORE ends half a second before the patient breathes out (the probe slid over
    sloping skin, then stood still): the end is dated where the wall leaves the still
    course, not where the slide stopped."""
    cfg = M.BreathingConfig(enabled=True, amplitude=0.015, rate_per_min=15.0)
    prompts = [(12.0, M.Prompt.HOLD_IN), (26.0, M.Prompt.BREATHE)]
    times, holds, s = breathe(
        cfg, prompts, 32.0, slope=0.2, speed=0.005, moving=lambda t: 15.0 <= t <= 26.0
    )
    on, off = true_hold_edges(times, holds)
    out_of = [w for w, d, a, b in s.transitions if a == R.HOLDING and on[0] < w < off[0] + 1]
    assert len(out_of) == 1 and abs(out_of[0] - off[0]) <= 0.3, (out_of, off)


def test_the_probes_own_turns_do_not_end_a_hold_and_its_end_is_found_after_them():
    """PIVOT in a hold: three tilts of 1 s each (commanded at 10 mm/s) change the wall's
    reading by 1.5 mm and back, as the recorded scans' TRANSIT and PIVOT did. Told how the
    scan moves the probe, the estimator keeps the hold through them and dates its end,
    which comes after the probe stopped, within 0.3 s; not told, it loses the hold. Gated
    free breathing asks for no hold: there any departure ends one at once, the probe's own
    motion or not (a breath in must stop the probe)."""
    cfg = M.BreathingConfig(enabled=True, amplitude=0.015, rate_per_min=15.0)
    prompts = [(12.0, M.Prompt.HOLD_IN), (26.0, M.Prompt.BREATHE)]
    tilts = [(16.0, 17.0), (19.0, 20.0), (22.0, 23.0)]

    def turn(t):
        return sum(0.0015 * math.sin(math.pi * (t - a) / (b - a)) for a, b in tilts if a <= t <= b)

    def own(t):
        return 0.01 if any(a <= t <= b for a, b in tilts) or 25.6 <= t <= 26.0 else 0.0005

    for told, mode in ((True, "breath_hold"), (False, "breath_hold"), (True, "gated")):
        times, holds, s = breathe(
            cfg, prompts, 32.0, turn=turn, own=own if told else None, mode=mode
        )
        on, off = true_hold_edges(times, holds)
        out_of = [w for w, d, a, b in s.transitions if a == R.HOLDING and on[0] < w < off[0] + 1]
        if told and mode == "breath_hold":
            assert len(out_of) == 1 and abs(out_of[0] - off[0]) <= 0.3, (out_of, off)
        else:
            assert len(out_of) > 1 and out_of[0] < off[0] - 1.0, out_of


def test_a_breaths_top_taken_for_a_hold_ends_when_the_wall_rises_on():
    """Told to hold at the top of a breath, the patient pauses there (a hold is sensed),
    then breathes in further and holds: the first "hold" ends when the wall rises on, and
    the real hold is dated where the wall stops, within 0.3 s."""
    rcfg = RespirationConfig(mode="breath_hold")
    s = R.RespirationState()
    times = np.arange(0.0, 24.0, DT)
    rng = np.random.default_rng(0)

    def wall(t):  # m: 4 s breaths of 3 mm; a pause at a top at 14 s, 2 mm more in 1 s
        if t < 14.0:
            return 0.0015 * (1.0 - math.cos(2.0 * math.pi * t / 4.0))
        if t < 15.0:
            return 0.003
        return 0.003 + 0.002 * min(1.0, (t - 15.0)) ** 2 * (3.0 - 2.0 * min(1.0, t - 15.0))

    for t in times:
        z = 0.2 + wall(t) + rng.normal(0, 2e-5)
        s = R.respiration_update(s, t, np.array([0.5, 0.0, z]), A_DOWN, 9.0, True, rcfg, 0.0)
    holds = [(w, a, b) for w, d, a, b in s.transitions if w > 13.0]
    onsets = [w for w, a, b in holds if b == R.HOLDING]
    assert any(a == R.HOLDING and b == R.BREATHING for _, a, b in holds), holds
    assert s.state == R.HOLDING and abs(onsets[-1] - 16.0) <= 0.3, holds


def test_own_motion_speed_adds_the_face_roll():
    assert R.own_motion_speed([0.003, 0.004, 0.0], [0.0, 0.0, 0.2]) == pytest.approx(
        0.005 + R.FACE_RADIUS * 0.2
    )


def test_hinge_change_point_finds_the_break_of_two_lines():
    t = np.arange(0.0, 0.8, DT)
    x = 0.001 - 0.0002 * t - 0.004 * np.maximum(t - 0.55, 0.0)
    assert R.hinge_change_point(t, x) == pytest.approx(0.55, abs=DT)


def test_a_patient_without_visible_breathing_is_still_a_hold():
    cfg = M.BreathingConfig(enabled=False)
    _, _, s = breathe(cfg, [], 6.0, wall=0.0)
    assert s.state == R.HOLDING and s.since < 1.0
    assert [b for _, _, _, b in s.transitions] == [R.HOLDING]


def _run_protocol(cfg, states, t_end, *, phase=1, ready=False):
    """protocol_step every DT with the estimator state ``states(t)`` -> (state, since)."""
    s = R.ProtocolState()
    log = []
    for t in np.arange(0.0, t_end, DT):
        st, since = states(t, s)
        s = R.protocol_step(s, t, phase, ready, st, since, cfg)
        log.append((t, s.allowed, s.prompt))
    return s, log


def test_protocol_breathes_first_asks_holds_splits_at_the_limit_and_rests():
    cfg = RespirationConfig(mode="breath_hold", hold_limit=10.0, recovery_time=5.0)

    def patient(t, s):  # holds 1 s after each "hold" prompt until told to breathe
        if s.prompt == 1 and t - s.prompted_at >= 1.0:
            return R.HOLDING, s.prompted_at + 1.0
        return R.BREATHING, 0.0

    s, log = _run_protocol(cfg, patient, 40.0)
    allowed = np.array([a for _, a, _ in log])
    t = np.array([x for x, _, _ in log])
    holds = [p for p in s.prompts if p[1] == 1]
    assert holds[0][0] == pytest.approx(5.0)  # recovery_time of free breathing first
    # Moves only in the holds, each at most hold_limit, with recovery between them.
    edges = np.diff(allowed.astype(int))
    starts, ends = t[1:][edges == 1], t[1:][edges == -1]
    assert starts[0] == pytest.approx(6.0, abs=0.02)
    assert ends[0] - starts[0] == pytest.approx(10.0, abs=0.02)
    assert starts[1] - ends[0] == pytest.approx(6.0, abs=0.02)  # rest 5 s + 1 s to hold
    assert s.holds >= 2 and [p[1] for p in s.prompts[:3]] == [1, 3, 1]


def test_protocol_asks_again_and_gives_up_when_no_hold_is_sensed():
    cfg = RespirationConfig(mode="breath_hold", recovery_time=1.0, hold_wait=2.0, max_prompts=3)
    s, log = _run_protocol(cfg, lambda t, s: (R.BREATHING, 0.0), 20.0)
    assert not any(a for _, a, _ in log)
    assert s.error.startswith("no breath-hold sensed after 3 prompts")


def test_protocol_tolerates_a_moment_of_doubt_but_not_a_let_go():
    cfg = RespirationConfig(mode="breath_hold", recovery_time=1.0)

    def patient(t, s):
        if 4.0 <= t < 4.5 or t >= 8.0:
            return R.BREATHING, 4.0
        return (R.HOLDING, 1.5) if s.prompt == 1 else (R.BREATHING, 0.0)

    s, log = _run_protocol(cfg, patient, 14.0)
    allowed = {round(t, 2): a for t, a, _ in log}
    assert allowed[3.0] and not allowed[4.2] and allowed[5.0]  # regained
    assert not allowed[13.0] and s.prompts[1][1] == M.Prompt.BREATHE  # let go: rest
    assert s.prompts[1][0] == pytest.approx(8.0 + R.REGAIN_TIME, abs=0.02)


def test_protocol_waits_out_a_stillness_that_began_before_the_prompt():
    """Still since before "breathe in and hold" (a breath's top, or a patient already
    holding): no motion until it has lasted ALREADY_HOLDING_CONFIRM past the prompt; a
    breath's top is over by then, a hold is not."""
    cfg = RespirationConfig(mode="breath_hold", recovery_time=1.0)
    top = lambda t, s: (R.HOLDING, 0.9) if t < 1.3 else (R.BREATHING, 1.3)  # noqa: E731
    s, log = _run_protocol(cfg, top, 3.0)
    assert s.prompts[0] == (pytest.approx(1.0), M.Prompt.HOLD_IN)
    assert not any(a for _, a, _ in log) and s.holds == 0
    held = lambda t, s: (R.HOLDING, 0.9)  # noqa: E731
    s, log = _run_protocol(cfg, held, 3.0)
    first = next(t for t, a, _ in log if a)
    assert first == pytest.approx(1.0 + R.ALREADY_HOLDING_CONFIRM, abs=0.02)
    assert s.hold_since == pytest.approx(1.0)  # counted from the prompt


def test_protocol_holds_for_transit_and_pivot_not_for_localize():
    cfg = RespirationConfig(mode="breath_hold")
    assert R.phase_needs_hold(1, False) and R.phase_needs_hold(4, False)
    assert not R.phase_needs_hold(2, False) and R.phase_needs_hold(2, True)
    assert not R.phase_needs_hold(0, False)
    s = R.ProtocolState(prompt=1, hold_since=3.0, rest_until=0.0, allowed=True)
    s = R.protocol_step(s, 5.0, 2, False, R.HOLDING, 3.0, cfg)  # LOCALIZE: breathe
    assert s.prompt == M.Prompt.BREATHE and not s.allowed
    assert s.rest_until == pytest.approx(5.0 + cfg.recovery_time)
    done = R.protocol_step(dataclasses.replace(s, prompt=1), 9.0, 5, False, R.HOLDING, 3.0, cfg)
    assert done.prompt == M.Prompt.BREATHE  # the scan ended: breathe normally


def test_gating_moves_only_at_end_expiration_or_in_a_hold():
    assert R.gate_step(1, R.END_EXPIRATION) and R.gate_step(4, R.HOLDING)
    assert not R.gate_step(1, R.BREATHING) and not R.gate_step(4, R.UNKNOWN)
    assert R.gate_step(2, R.BREATHING) and R.gate_step(3, R.BREATHING)


def test_prompter_prints_each_new_prompt_once(capsys):
    import io

    from pydrake.systems.analysis import Simulator

    stream = io.StringIO()
    prompter = BreathPrompter(0.01, speak=False, stream=stream)
    sim = Simulator(prompter)
    ctx = sim.get_mutable_context()
    port = prompter.GetInputPort("breath_prompt")
    for t, p in ((0.5, 0), (1.0, 1), (1.5, 1), (2.0, 3)):
        port.FixValue(ctx, [float(p)])
        sim.AdvanceTo(t)
    lines = stream.getvalue().splitlines()
    assert len(lines) == 2 and "breathe in ... and hold" in lines[0]
    assert "breathe normally" in lines[1]
    command = speech_command("hold")
    assert command is None or command[-1] == "hold"
