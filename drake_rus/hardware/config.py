"""Scenario section ``hardware_interface``: how the hardware station reaches the real setup.

Used only when the scenario says ``hardware: true``. Units are SI (m, rad, s); rates in Hz.
Client-side limits sit below the FR3's own (docs/facts/fr3.md: joint velocity rectangular set
[2, 1, 1.5, 1.25, 3, 1.5, 3] rad/s, joint acceleration 10 rad/s^2): the robot's limits stay
the last line of defence, ours act first.
"""

from dataclasses import dataclass, field

from drake_rus.config_schema import physical

__all__ = ["HardwareConfig", "BACKENDS"]

BACKENDS = ["franky", "lcm"]


@dataclass
class HardwareConfig:
    # Robot client: "franky" (franky-control, libfranka 0.21 over the FCI network protocol,
    # joint-velocity motions) or "lcm" (drake-franka-driver: PANDA_COMMAND / PANDA_STATUS).
    backend: str = field(default="franky", metadata={"choices": BACKENDS})
    # FCI address of the robot (franky backend): an IPv4 address or a host name.
    robot_ip: str = "172.16.0.2"
    # Connect and read (joints, torques, images) but never command motion: every command
    # sent is zero, whatever the controller asks.
    dry_run: bool = True
    # Rate (Hz) at which velocity targets are sent; normally the controller's rate_hz. The
    # 1 kHz loop stays in the library (franky) or the driver (lcm).
    command_rate_hz: float = field(
        default=200.0,
        metadata=physical(
            10.0, 1000.0, "Hz", "velocity targets at most at the FR3's 1 kHz", positive=True
        ),
    )
    # Client-side joint velocity limits (rad/s): commands are scaled into them (direction
    # kept). Default: 40 % of the FR3 rectangular set.
    max_joint_velocity: list[float] = field(
        default_factory=lambda: [0.8, 0.4, 0.6, 0.5, 1.2, 0.6, 1.2],
        metadata={"length": 7, "positive": True, "max": 3.0},
    )
    # Client-side joint acceleration limits (rad/s^2) on the command (FR3: 10 rad/s^2).
    max_joint_acceleration: list[float] = field(
        default_factory=lambda: [2.0] * 7, metadata={"length": 7, "positive": True, "max": 10.0}
    )
    # Command watchdog (s): no fresh command from the diagram for this long -> zero velocity
    # (franky: each target expires after this long inside the library as well; LCM: run
    # drake-franka-driver with --expire_sec equal to this). Sized for a busy 2-core PC:
    # the control loop's tick gaps measured there (LCM route, simulated driver, video, load
    # 2-5.5) had a 99.9th percentile of 31-70 ms and a 99.99th of 49-110 ms (six 60 s runs,
    # docs/hardware_bringup.md "Watchdog timing"); 0.15 s is twice the worst 99.9th. A
    # longer stall is a frozen process: the robot stops. On a real-time PC: 0.05.
    command_timeout: float = field(default=0.15, metadata={"positive": True, "max": 1.0})
    # Robot state watchdog (s): no fresh robot state for this long -> connection lost. A
    # stall of our own loop is not taken for a lost robot (the LCM status latch waits for
    # a few of its own ticks without news after a stall; franky's state is refreshed by
    # libfranka's own thread). On a real-time PC: 0.1.
    status_timeout: float = field(default=0.25, metadata={"positive": True, "max": 2.0})
    # Connection attempts (s) before giving up at start.
    connect_timeout: float = field(default=10.0, metadata={"positive": True})
    # franky's global relative dynamics factor in (0, 1] (its Ruckig limits on the targets).
    relative_dynamics_factor: float = field(default=0.2, metadata={"positive": True, "max": 1.0})
    # Tell libfranka the probe holder's load (scenario probe.mass, p_FCm, inertia_diagonal)
    # at connection, so its external torque estimate excludes the probe's weight (franky).
    set_load: bool = True
    # LCM route: drake-franka-driver never calls libfranka's setLoad and FCI takes a single
    # client, so the load cannot be declared from here. Best: enter the probe holder in
    # Desk as the end effector (mass, centre of mass, inertia; the robot's own collision
    # detection then knows it too) and set this false. true (default, for a Desk that does
    # not know the probe): the station removes the probe's weight from the driver's external
    # torques itself (J_Cm(q)^T m g from our FR3 model, probe.mass, probe.p_FCm). An
    # unaccounted weight reads as a pull on the probe (a probe pointing down then presses up
    # to m g harder than it reads); a weight removed twice reads as a push (it presses less:
    # the safe side). `drake-rus hardware check` says which the torques at rest match.
    lcm_compensate_load: bool = True
    # Subtract the external joint torque read at rest at start-up (seconds of averaging; 0
    # disables): the FR3's estimate carries a configuration-dependent offset in free space.
    tau_external_bias_duration: float = field(default=0.2, metadata={"min": 0.0, "max": 5.0})

    # --- Robot-side safety: the FR3's own reflexes (franky: set at connection) ---
    # Set libfranka's collision behavior (setCollisionBehavior) at connection. Between the
    # "contact" and "collision" thresholds the robot only flags a contact
    # (RobotState.joint_contact / cartesian_contact); above "collision" it aborts the motion
    # with a reflex (joint_reflex / cartesian_reflex), the run ends with HardwareFault and
    # the robot refuses motion until its errors are reset (error_recovery). The same values
    # hold while accelerating and at constant velocity. franky's own defaults (20 N m,
    # 30 N) would let the probe press harder than the safety layer's 20 N ceiling.
    set_collision_behavior: bool = True
    # Joint torque thresholds (N m), joints 1-7. A 20 N push along the probe axis at the
    # initial scan posture loads joint 2 with 11.7 N m and joint 4 with 9.1 N m; the torque
    # estimate errs by a few N m in motion, so these guard the arm (elbow against the bed),
    # and the Cartesian thresholds below guard the probe face.
    contact_torque_thresholds: list[float] = field(
        default_factory=lambda: [10.0, 10.0, 9.0, 9.0, 8.0, 7.0, 6.0],
        metadata={"length": 7, "positive": True, "max": 100.0},
    )
    collision_torque_thresholds: list[float] = field(
        default_factory=lambda: [20.0, 20.0, 18.0, 18.0, 16.0, 14.0, 12.0],
        metadata={"length": 7, "positive": True, "max": 100.0},
    )
    # Cartesian thresholds on the wrench estimate at the stiffness frame K (the flange
    # unless an end effector is set in Desk): [fx, fy, fz] (N), [mx, my, mz] (N m). Collision
    # forces sit below the safety layer's 20 N force ceiling (safety.force_ceiling); the
    # moments allow 18 N at the probe tip 0.2 m from the flange (3.6 N m).
    contact_force_thresholds: list[float] = field(
        default_factory=lambda: [10.0, 10.0, 10.0, 2.0, 2.0, 2.0],
        metadata={"length": 6, "positive": True, "max": 100.0},
    )
    collision_force_thresholds: list[float] = field(
        default_factory=lambda: [18.0, 18.0, 18.0, 4.0, 4.0, 4.0],
        metadata={"length": 6, "positive": True, "max": 100.0},
    )
    # A robot that stopped with a reflex (or the user stop) has errors pending and refuses
    # motion until they are reset (libfranka automaticErrorRecovery, franky
    # recover_from_errors). "operator": never reset by the software; connecting to a robot
    # with errors pending is a HardwareFault that says what to do (the operator checks the
    # patient and the probe, then runs `drake-rus hardware check --recover` or resets in
    # Desk). "at_connect": reset at connection, logged. Never reset during a run.
    error_recovery: str = field(
        default="operator", metadata={"choices": ["operator", "at_connect"]}
    )

    # --- Frame grabber (the ultrasound machine's video output) ---
    # The video source: a capture device index ("0", "1", ...), a video file path (replayed
    # at its own frame rate in real time) or a stream URL that OpenCV's VideoCapture opens
    # (http(s):// MJPEG, rtsp://, rtp://, udp://, tcp://). Empty: no grabber; the station
    # then exports blank, unstamped frames. A capture thread drains the source
    # continuously and keeps only the newest picture with its capture time.
    video_source: str = ""
    # Loop a video file when it ends (replay); a device or a stream never ends.
    video_loop: bool = True
    # Crop rectangle of the ultrasound sector in the grabbed picture (pixels): [x, y, width,
    # height] with (x, y) the top-left corner; width = height = 0 keeps the whole picture.
    # Used only without image_calibration (the calibration file has a crop per depth).
    video_crop: list[int] = field(
        default_factory=lambda: [0, 0, 0, 0], metadata={"length": 4, "min": 0}
    )
    # Image calibration file (YAML, drake_rus/hardware/image_calibration.py; written by
    # `drake-rus hardware calibrate-image`): per depth preset the crop, mm per pixel and the
    # pixel of the probe-face centre, plus the image-to-probe transform. The entry for
    # imaging.depth maps every grabbed picture onto the probe's image grid
    # (ProbeGeometry), so segmentation and back-projection are metric. Empty: the crop is
    # only stretched to the image size (not metric; a warning says so).
    image_calibration: str = ""
    # Video latency (s): from the moment the beam sweeps the tissue to the moment the
    # capture thread receives the picture (scan conversion, video output, capture card,
    # USB, decoding), plus the robot state's own lag. Each frame carries the probe pose at
    # (capture time - video_latency), interpolated from the pose history, and the diagram
    # time of that instant. Measure it with `drake-rus hardware calibrate-latency`.
    video_latency: float = field(default=0.0, metadata={"min": 0.0, "max": 1.0})
    # Length (s) of the probe pose history (ring buffer, filled every control period).
    pose_history: float = field(default=2.0, metadata={"positive": True, "max": 60.0})

    # --- LCM backend (drake-franka-driver) ---
    lcm_url: str = "udpm://239.255.76.67:7667?ttl=0"
    lcm_command_channel: str = "PANDA_COMMAND"
    lcm_status_channel: str = "PANDA_STATUS"
