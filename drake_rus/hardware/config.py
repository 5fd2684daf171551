"""Scenario section ``hardware_interface``: how the hardware station reaches the real setup.

Used only when the scenario says ``hardware: true``. Units are SI (m, rad, s); rates in Hz.
Client-side limits sit below the FR3's own (docs/facts/fr3.md: joint velocity rectangular set
[2, 1, 1.5, 1.25, 3, 1.5, 3] rad/s, joint acceleration 10 rad/s^2): the robot's limits stay
the last line of defence, ours act first.
"""

from dataclasses import dataclass, field

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
    command_rate_hz: float = field(default=200.0, metadata={"positive": True, "max": 1000.0})
    # Client-side joint velocity limits (rad/s): commands are scaled into them (direction
    # kept). Default: 40 % of the FR3 rectangular set.
    max_joint_velocity: list[float] = field(
        default_factory=lambda: [0.8, 0.4, 0.6, 0.5, 1.2, 0.6, 1.2],
        metadata={"length": 7, "positive": True, "max": 3.0})
    # Client-side joint acceleration limits (rad/s^2) on the command (FR3: 10 rad/s^2).
    max_joint_acceleration: list[float] = field(
        default_factory=lambda: [2.0] * 7,
        metadata={"length": 7, "positive": True, "max": 10.0})
    # Command watchdog (s): no fresh command from the diagram for this long -> zero velocity
    # (franky: each target expires after this long inside the library as well).
    command_timeout: float = field(default=0.05, metadata={"positive": True, "max": 1.0})
    # Robot state watchdog (s): no fresh robot state for this long -> connection lost.
    status_timeout: float = field(default=0.1, metadata={"positive": True, "max": 2.0})
    # Connection attempts (s) before giving up at start.
    connect_timeout: float = field(default=10.0, metadata={"positive": True})
    # franky's global relative dynamics factor in (0, 1] (its Ruckig limits on the targets).
    relative_dynamics_factor: float = field(default=0.2, metadata={"positive": True,
                                                                   "max": 1.0})
    # Tell libfranka the probe holder's load (scenario probe.mass, p_FCm, inertia_diagonal)
    # at connection, so its external torque estimate excludes the probe's weight (franky).
    set_load: bool = True
    # Subtract the external joint torque read at rest at start-up (seconds of averaging; 0
    # disables): the FR3's estimate carries a configuration-dependent offset in free space.
    tau_external_bias_duration: float = field(default=0.2, metadata={"min": 0.0, "max": 5.0})

    # --- Frame grabber (the ultrasound machine's video output) ---
    # OpenCV VideoCapture source: a capture device index ("0", "1", ...) or a video file
    # path (replay). Empty: no grabber; the station then exports blank, unstamped frames.
    video_source: str = ""
    # Loop a video file when it ends (replay); a device never ends.
    video_loop: bool = True
    # Crop rectangle of the ultrasound sector in the grabbed picture (pixels): [x, y, width,
    # height] with (x, y) the top-left corner; width = height = 0 keeps the whole picture.
    video_crop: list[int] = field(default_factory=lambda: [0, 0, 0, 0],
                                  metadata={"length": 4, "min": 0})

    # --- LCM backend (drake-franka-driver) ---
    lcm_url: str = "udpm://239.255.76.67:7667?ttl=0"
    lcm_command_channel: str = "PANDA_COMMAND"
    lcm_status_channel: str = "PANDA_STATUS"
