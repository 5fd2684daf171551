"""``drake-rus hardware``: bring-up commands for the real robot and ultrasound machine
(docs/hardware_bringup.md).

    drake-rus hardware check --dry-run --set "{hardware_interface: {robot_ip: 172.16.0.2}}"

- ``check``: connect, read; live read-outs (joints, contact force, video rate and age) at a
  few Hz; the push test in a dry run; with ``--no-dry-run`` a short scripted motion in free
  space. Exit 0: every check of the guide passed; 1: one was missed (named); 2: no
  connection or a bad configuration.
- ``pivot``: live read-outs while the operator pivots the probe tip in a divot, then the
  pivot calibration of the tip (exit 1 above the guide's residuals).
- ``grab``: saves the newest grabbed picture and the joint positions (for calibrate-image).
- ``calibrate-image``: scale and origin of the picture per depth preset from point-target
  pictures (least squares), written to the image calibration file.
- ``calibrate-latency``: moves the probe sinusoidally over a point target and estimates the
  video latency.

The procedures (checks, scripted motion, read-outs, calibrations) are the library
``drake_rus.bringup``; this module parses arguments, connects and reports.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
from pydrake.common.yaml import yaml_dump_typed

from drake_rus.bringup import (
    BuildHardwareClosedLoop,
    CheckStation,
    Readout,
    RecordPivot,
    RunLatencyCalibration,
    image_fit_failures,
    pivot_failures,
)
from drake_rus.cli import add_scenario_arguments
from drake_rus.config_schema import ScenarioError
from drake_rus.extras import require
from drake_rus.hardware.calibration import flange_poses_from_joints, pivot_calibration
from drake_rus.hardware.image_calibration import (
    ImageCalibration,
    TargetImage,
    TargetSet,
    find_point_target,
    fit_target_set,
    load_image_calibration,
    load_target_set,
    save_image_calibration,
    with_preset,
)
from drake_rus.hardware.station import HardwareFault, MakeHardwareStation
from drake_rus.io_utils import write_text_atomic
from drake_rus.scenario import ApplyOverrides, LoadScenario

__all__ = ["add_commands"]


def _load(args, **hardware) -> object:
    scenario = LoadScenario(
        filename=args.scenarios_file, scenario_name=args.scenario, scenario_text=args.overrides
    )
    fields = ", ".join(f"{k}: {v}" for k, v in hardware.items())
    return ApplyOverrides(scenario, "{hardware: true, hardware_interface: {%s}}" % fields)


def _connect(scenario, prog: str, **kwargs):
    try:
        return MakeHardwareStation(scenario, **kwargs)
    except (HardwareFault, ValueError) as e:  # ScenarioError is a ValueError
        print(f"drake-rus hardware {prog}: error: {e}", file=sys.stderr)
        return None


def _report(prog: str, failures: list[str]) -> int:
    if failures:
        print(f"drake-rus hardware {prog}: FAILED:")
        for f in failures:
            print(f"  - {f}")
        return 1
    print(f"drake-rus hardware {prog}: all checks passed")
    return 0


def add_commands(subparsers) -> None:
    p = subparsers.add_parser(
        "hardware",
        help="the real robot: connection check, dry run, scripted motion, calibrations",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="hardware_command", metavar="HARDWARE_COMMAND")
    sub.required = True

    def common(c, readout=True):
        add_scenario_arguments(c)
        c.add_argument(
            "--recover",
            action="store_true",
            help="reset the robot's pending errors at connection (after you "
            "checked the patient and the probe)",
        )
        if readout:
            c.add_argument(
                "--readout-hz",
                type=float,
                default=4.0,
                help="live read-outs per second (0: none; default 4)",
            )

    c = sub.add_parser(
        "check",
        help="connect, read joints / torques / images with live "
        "read-outs and the push test; with --no-dry-run also run the scripted "
        "free-space motion",
    )
    common(c)
    group = c.add_mutually_exclusive_group()
    group.add_argument(
        "--dry-run",
        dest="dry_run",
        action="store_true",
        default=True,
        help="read only, never command motion (default)",
    )
    group.add_argument(
        "--no-dry-run",
        dest="dry_run",
        action="store_false",
        help="also run the scripted motion: 5 deg tilt, 2 cm slide, no contact",
    )
    c.add_argument(
        "--duration",
        type=float,
        default=2.0,
        help="seconds of reading in a dry run (default 2; 20-30 for the push test)",
    )
    c.add_argument(
        "--rest",
        type=float,
        default=1.0,
        help="first seconds of a dry run with nothing touching the probe (default 1)",
    )
    c.set_defaults(func=run_check)

    c = sub.add_parser(
        "pivot",
        help="pivot calibration of the probe tip: live read-outs "
        "while you pivot the tip in a divot, then the fit",
    )
    common(c)
    c.add_argument("--duration", type=float, default=60.0, help="seconds of recording (default 60)")
    c.add_argument(
        "--rate", type=float, default=10.0, help="joint samples per second recorded (default 10)"
    )
    c.add_argument(
        "--save",
        default=None,
        metavar="CSV",
        help="also write the recorded joint positions (rad) to this file",
    )
    c.set_defaults(func=run_pivot, outputs={"save": "file"})

    c = sub.add_parser(
        "grab",
        help="save the newest grabbed picture and the joint "
        "positions, and list them in a target file for calibrate-image",
    )
    common(c, readout=False)
    c.add_argument(
        "--out",
        default="image_targets",
        metavar="DIR",
        help="folder of pictures and targets.yaml (default image_targets)",
    )
    c.add_argument(
        "--p-P",
        dest="p_P",
        type=float,
        nargs=3,
        default=None,
        metavar=("X", "Y", "Z"),
        help="the target's position in the probe frame (m), if known (a jig)",
    )
    c.set_defaults(func=run_grab, outputs={"out": "dir"})

    c = sub.add_parser(
        "calibrate-image",
        help="fit mm per pixel and the image origin of a "
        "depth preset to point-target pictures; write the calibration file",
    )
    add_scenario_arguments(c)
    c.add_argument("targets", help="target file (YAML, see `hardware grab`)")
    c.add_argument("--out", required=True, help="image calibration file to write or update")
    c.add_argument(
        "--force",
        action="store_true",
        help="write even when the residuals exceed the guide's limits",
    )
    c.set_defaults(func=run_calibrate_image, outputs={"out": "file"})

    c = sub.add_parser(
        "calibrate-latency",
        help="move the probe sinusoidally over a point "
        "target (in water or a phantom) and estimate the video latency",
    )
    common(c)
    c.add_argument(
        "--amplitude",
        type=float,
        default=0.01,
        help="motion amplitude along the probe's array (m, default 0.01)",
    )
    c.add_argument("--period", type=float, default=2.0, help="motion period (s, default 2)")
    c.add_argument("--cycles", type=float, default=4.0, help="periods (default 4)")
    c.add_argument(
        "--max-latency", type=float, default=0.5, help="largest latency considered (s, default 0.5)"
    )
    c.set_defaults(func=run_calibrate_latency)


def run_check(args) -> int:
    scenario = _load(
        args,
        dry_run="true" if args.dry_run else "false",
        **({"error_recovery": "at_connect"} if args.recover else {}),
    )
    station = _connect(scenario, "check")
    if station is None:
        return 2
    try:
        failures = CheckStation(
            scenario,
            station,
            dry_run=args.dry_run,
            duration=args.duration,
            rest=args.rest,
            readout_hz=args.readout_hz,
        )
        return _report("check", failures)
    except HardwareFault as e:
        print(f"drake-rus hardware check: error: {e}", file=sys.stderr)
        return 2
    finally:
        station.close()


def run_pivot(args) -> int:
    scenario = _load(
        args, dry_run="true", **({"error_recovery": "at_connect"} if args.recover else {})
    )
    station = _connect(scenario, "pivot")
    if station is None:
        return 2
    try:
        print(
            f"pivot the probe tip in the divot for {args.duration:g} s: tilt 20-40 deg "
            f"about two different axes, the tip never leaving the divot"
        )
        q = RecordPivot(station, args.duration, args.rate, args.readout_hz)
    except HardwareFault as e:
        print(f"drake-rus hardware pivot: error: {e}", file=sys.stderr)
        return 2
    finally:
        station.close()
    if args.save:
        np.savetxt(args.save, q, delimiter=",", header="q1,q2,q3,q4,q5,q6,q7 (rad)")
        print(f"joint positions: {args.save} ({len(q)} samples)")
    try:
        cal = pivot_calibration(*flange_poses_from_joints(scenario, q))
    except ValueError as e:
        print(f"drake-rus hardware pivot: {e}", file=sys.stderr)
        return 1
    print(
        f"tip in the flange p_FT = {np.array2string(cal.p_FT, precision=5)} m; pivot "
        f"p_BT = {np.array2string(cal.p_BT, precision=4)} m"
    )
    print(
        f"residuals: RMS {1e3 * cal.rms:.2f} mm, max {1e3 * cal.residuals.max():.2f} mm over "
        f"{len(q)} samples; write p_FT into probe.X_FP.translation"
    )
    return _report("pivot", pivot_failures(cal))


def run_grab(args) -> int:
    scenario = _load(
        args, dry_run="true", **({"error_recovery": "at_connect"} if args.recover else {})
    )
    if not scenario.hardware_interface.video_source.strip():
        print(
            "drake-rus hardware grab: error: field 'hardware_interface.video_source' is empty",
            file=sys.stderr,
        )
        return 2
    station = _connect(scenario, "grab", keep_raw_pictures=True)
    if station is None:
        return 2
    try:
        cv2 = require("cv2", "hardware grab")
        frame = station.grabber.capture.wait_for(-1, timeout=5.0)
        if frame is None or frame.picture is None:
            print("drake-rus hardware grab: error: no picture within 5 s", file=sys.stderr)
            return 2
        q = np.array(station.GetOutputPort("joint_position").Eval(station.CreateDefaultContext()))
    finally:
        station.close()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    index_file = out / "targets.yaml"
    targets = (
        load_target_set(index_file)
        if index_file.exists()
        else TargetSet(
            depth=scenario.imaging.depth, crop=list(scenario.hardware_interface.video_crop)
        )
    )
    name = f"grab_{len(targets.targets):03d}.png"
    cv2.imwrite(str(out / name), frame.picture)
    targets.targets.append(
        TargetImage(
            image=name,
            p_P=list(args.p_P) if args.p_P else [],
            q=[] if args.p_P else [float(v) for v in q],
        )
    )
    write_text_atomic(index_file, yaml_dump_typed(targets))  # a cut-off index loses targets
    found = find_point_target(
        frame.picture, targets.crop, targets.search_radius_px, targets.min_contrast
    )
    where = (
        f"target at column {found[0]:.1f}, row {found[1]:.1f}"
        if found is not None
        else "NO target found: check the crop and the gain"
    )
    print(
        f"{out / name}: {where}; q = {np.array2string(q, precision=4)} rad; listed in "
        f"{index_file} ({len(targets.targets)} pictures, depth {targets.depth:g} m)"
    )
    return 0 if found is not None else 1


def run_calibrate_image(args) -> int:
    prog = "drake-rus hardware calibrate-image"
    try:
        targets = load_target_set(args.targets)
        scenario = LoadScenario(
            filename=args.scenarios_file, scenario_name=args.scenario, scenario_text=args.overrides
        )
        report = fit_target_set(targets, Path(args.targets).parent, scenario)
    except ValueError as e:  # ScenarioError too
        print(f"{prog}: refused: {e}", file=sys.stderr)
        return 2
    fit = report.fit
    print(
        f"depth {targets.depth:g} m: {fit.mm_per_pixel[0]:.4f} x {fit.mm_per_pixel[1]:.4f} "
        f"mm per pixel; origin (probe-face centre) at column {fit.origin_px[0]:.1f}, row "
        f"{fit.origin_px[1]:.1f}; in-plane angle {fit.angle_deg:+.2f} deg; mirrored: "
        f"{str(fit.mirror_x).lower()}; skew {fit.skew_deg:+.2f} deg"
    )
    for name, px, p, r in zip(report.names, report.pixels, report.p_P, fit.residuals_mm):
        print(
            f"  {name}: target at ({px[0]:7.1f}, {px[1]:7.1f}) px, p_P = "
            f"({1e3 * p[0]:+7.1f}, {1e3 * p[2]:+7.1f}) mm (x, z): residual {r:.2f} mm"
        )
    print(
        f"residuals: RMS {fit.rms_mm:.2f} mm, max {fit.max_residual_mm:.2f} mm over "
        f"{len(report.names)} targets"
    )
    failures = image_fit_failures(fit)
    if len(report.names) < 6:
        print(f"note: {len(report.names)} targets; 6 or more give a check on the fit")
    if failures and not args.force:
        print(
            f"{prog}: not written ({'; '.join(failures)}); re-take the worst pictures or "
            f"use --force"
        )
        return 1
    out = Path(args.out)
    try:
        cal = load_image_calibration(out) if out.exists() else ImageCalibration()
    except ScenarioError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    old = cal.X_PI.GetDeterministicValue()
    cal = with_preset(
        cal, fit.preset(targets.depth, targets.crop), angle_deg=fit.angle_deg, mirror_x=fit.mirror_x
    )
    if cal.presets and len(cal.presets) > 1:
        new = cal.X_PI.GetDeterministicValue()
        turn = math.degrees(
            np.arccos(
                np.clip(
                    (np.trace(old.rotation().matrix().T @ new.rotation().matrix()) - 1) / 2, -1, 1
                )
            )
        )
        if turn > 1.0:
            print(
                f"warning: the in-plane angle moved by {turn:.1f} deg from the file's; the "
                f"other presets were fitted with the old one"
            )
    save_image_calibration(cal, out)
    print(
        f"wrote {out} (entries for {', '.join(f'{p.depth:g}' for p in cal.presets)} m); "
        f"set hardware_interface.image_calibration: {out}"
    )
    return 1 if failures else 0


def run_calibrate_latency(args) -> int:
    prog = "calibrate-latency"
    scenario = _load(
        args,
        dry_run="false",
        video_latency=0.0,
        **({"error_recovery": "at_connect"} if args.recover else {}),
    )
    station = _connect(scenario, prog)
    if station is None:
        return 2
    try:
        loop = BuildHardwareClosedLoop(scenario, station)
        print(
            f"moving the probe {1e3 * args.amplitude:g} mm each way along its array, "
            f"period {args.period:g} s, {args.cycles:g} periods, over the point target"
        )
        holder = {}

        def on_step():
            if "readout" not in holder:
                holder["readout"] = Readout(
                    station, station.GetMyContextFromRoot(holder["root"]), args.readout_hz
                )
            holder["readout"].step()

        result = RunLatencyCalibration(
            loop,
            station,
            amplitude=args.amplitude,
            period=args.period,
            cycles=args.cycles,
            max_latency=args.max_latency,
            on_step=on_step,
            context_out=holder,
        )
    except ValueError as e:
        print(f"drake-rus hardware {prog}: refused: {e}", file=sys.stderr)
        return 1
    except HardwareFault as e:
        print(f"drake-rus hardware {prog}: error: {e}", file=sys.stderr)
        return 2
    finally:
        station.close()
    est = result.estimate
    print(
        f"video latency {1e3 * est.latency:.1f} ms (correlation {est.correlation:+.3f}, "
        f"{est.frames} frames)"
    )
    print(f"set hardware_interface.video_latency: {est.latency:.3f}")
    return 0
