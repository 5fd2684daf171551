"""The simulated side of a rehearsal: the virtual patient's station behind drake-franka-driver's
wire, with the ultrasound machine's video output.

:func:`BuildRehearsalSim` puts the simulated station (``drake_rus.station.MakeSimStation``:
FR3 + probe + soft patient, slice sensor and ultrasound emulator) behind
:func:`drake_rus.hardware.lcm_sim_driver.AddSimulatedDriverWire` (PANDA_COMMAND in, velocity
mode, the driver's command expiry; PANDA_STATUS out, wall-clock stamps, the driver's torque
sign); its station makes no ultrasound frames. :class:`RehearsalSim` runs it paced at real
time (:meth:`RehearsalSim.run`) and, at each imaging instant, hands the pose a picture is
rendered from (``drake_rus.rehearsal.video_process.PoseSnapshot``) to the video output.

Only the physics steps in the simulation's own thread. What need not be there runs beside
it, so that the robot keeps its status rate: the statuses are published on their own
wall-clock schedule (the newest state the simulation handed them, stamped when sent) by
``status_process.StatusPublisherProcess`` on udpm (a process: no interpreter lock shared
with the physics) or :class:`StatusPublisherThread`, and the ultrasound pictures are
sliced, emulated (the station's own functions, model and seed: the picture its
``us_image`` would give) and JPEG-encoded in a process of their own
(``video_process.VideoProcess``), never in the physics thread and not under its
interpreter lock.

The reported external torque: the station's contact torques plus, with
``undeclared_load`` (the LCM route's situation: drake-franka-driver cannot declare the
probe's load to the robot), the probe's weight as the real robot would report it; the scan
side then removes it (``hardware_interface.lcm_compensate_load``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from typing import Callable

import numpy as np
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem

from drake_rus.hardware.core import wall_clock_utime
from drake_rus.hardware.lcm_sim_driver import DRIVER_EXPIRE_SEC, AddSimulatedDriverWire
from drake_rus.hardware.systems import ProbeLoadTorque
from drake_rus.pacing import GcPauses, gc_statistics, loop_statistics, percentiles_ms
from drake_rus.rehearsal.core import PivotDetector, realtime_scheduling
from drake_rus.rehearsal.video_process import PoseSnapshot
from drake_rus.rehearsal.wiretap import LcmUdpmTap
from drake_rus.robot import NUM_JOINTS, MakeControlPlant, contact_force_along_approach
from drake_rus.station import MakeSimStation

LOG = logging.getLogger("drake_rus.rehearsal")

__all__ = [
    "WireFaults",
    "BuildRehearsalSim",
    "RehearsalSim",
    "StatusPublisherThread",
    "ProbeWeightTorque",
]


@dataclasses.dataclass
class WireFaults:
    """Faults on the wire between the scan and the simulated robot and machine.

    ``command_latency`` (s): every command reaches the robot this much later;
    ``status_drop`` (probability): each status packet is lost with it; ``video_delay`` (s):
    the video output shows each picture this much later; ``freeze_video_at`` (s after the
    robot's first command, None: never): the picture freezes (the stream keeps flowing,
    like the machine's freeze key)."""

    command_latency: float = 0.0
    status_drop: float = 0.0
    video_delay: float = 0.0
    freeze_video_at: float | None = None

    def __post_init__(self):
        for name in ("command_latency", "video_delay"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name}: expected a non-negative time in s, got {value}")
        if not 0.0 <= self.status_drop <= 1.0:
            raise ValueError(
                f"status_drop: expected a probability in [0, 1], got {self.status_drop}"
            )
        if self.freeze_video_at is not None and not self.freeze_video_at >= 0.0:
            raise ValueError(f"freeze_video_at: expected a time >= 0 s, got {self.freeze_video_at}")


# How often (s) a waiting simulation handles arriving LCM messages.
WAIT_POLL = 0.5e-3


class StatusPublisherThread:
    """Publishes PANDA_STATUS on ``lcm`` every ``period`` s of the wall clock from its own
    thread: the newest status the simulation offered (``offer(msg)``), stamped with the
    wall clock when sent, each dropped with ``drop_probability`` (seeded by ``seed``). So
    the robot's status rate does not depend on how long a simulation step takes. Counts
    ``published`` and ``dropped``; ``times`` (monotonic s) of every status sent or
    dropped. ``start()``; ``close()``.

    ``realtime_priority`` (1-99; 0: none): the thread asks for the real-time scheduling
    class (SCHED_FIFO) at that priority, as a robot's own controller has it; without the
    permission (root or CAP_SYS_NICE) it runs as any thread. ``scheduling`` says which."""

    def __init__(
        self,
        lcm,
        channel: str,
        period: float,
        *,
        drop_probability: float = 0.0,
        seed: int = 0,
        realtime_priority: int = 0,
    ):
        import drake

        self._type = drake.lcmt_panda_status
        self._lcm, self._channel, self.period = lcm, channel, float(period)
        self._p = float(drop_probability)
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._latest = None
        self._stop = threading.Event()
        self.published = 0
        self.dropped = 0
        self.times: list[float] = []
        self.realtime_priority = int(realtime_priority)
        self.scheduling = "normal"
        self._thread = threading.Thread(
            target=self._run, name="drake_rus_panda_status", daemon=True
        )

    def offer(self, msg) -> None:
        copy = self._type.decode(msg.encode())  # this thread's own copy
        with self._lock:
            self._latest = copy

    def start(self) -> None:
        if not self._thread.is_alive():
            self._thread.start()

    def _run(self):
        if self.realtime_priority > 0:
            self.scheduling = realtime_scheduling(self.realtime_priority)
        due = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            if now < due:
                self._stop.wait(due - now)
                continue
            with self._lock:
                msg = self._latest
            if msg is not None:
                self.times.append(now)
                if self._p > 0.0 and self._rng.random() < self._p:
                    self.dropped += 1
                else:
                    msg.utime = wall_clock_utime()
                    self._lcm.Publish(self._channel, msg.encode())
                    self.published += 1
            due += self.period
            if due < now - self.period:  # fell behind (a stall): do not burst
                due = now + self.period

    def gaps_ms(self) -> dict:
        """p50, p99, p99.9 and max (ms) of the gaps between successive statuses."""
        t = np.asarray(self.times, float)
        return percentiles_ms(np.diff(t) if t.size > 1 else [])

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)


class ProbeWeightTorque(LeafSystem):
    """Inputs ``joint_position`` (7), ``tau_external`` (7, N m, Drake's sign). Output
    ``tau_external`` (7): plus the probe's weight as a robot that was not told about the
    probe reports it (``hardware.systems.ProbeLoadTorque``)."""

    def __init__(self, scenario):
        super().__init__()
        plant, _ = MakeControlPlant(scenario.robot, scenario.probe)
        self._plant = plant  # keep the model alive with its Jacobian helper
        self._load = ProbeLoadTorque(plant, scenario.probe.mass, scenario.probe.p_FCm)
        self._q = self.DeclareVectorInputPort("joint_position", NUM_JOINTS)
        self._tau = self.DeclareVectorInputPort("tau_external", NUM_JOINTS)
        self.DeclareVectorOutputPort(
            "tau_external",
            NUM_JOINTS,
            lambda c, o: o.SetFromVector(
                np.asarray(self._tau.Eval(c), float) + self._load(self._q.Eval(c))
            ),
        )


def BuildRehearsalSim(
    scenario,
    patient,
    lcm,
    *,
    faults: WireFaults,
    rate_hz: float = 200.0,
    expire_sec: float = DRIVER_EXPIRE_SEC,
    undeclared_load: bool = True,
    seed: int = 0,
    command_channel: str = "PANDA_COMMAND",
    status_channel: str = "PANDA_STATUS",
    status_sink: Callable | None = None,
):
    """The rehearsal's simulated robot, patient and machine as one Diagram; returns
    ``(diagram, station, wire)`` (see the module doc). ``scenario``: the simulated scenario
    already prepared for the scan's start (``drake_rus.scan.run.PrepareScenario``). The
    station slices no frames (its ``slice_sensor`` gives the poses to render at, see
    :class:`RehearsalSim`). ``status_sink(msg)``: each status, for a
    :class:`StatusPublisherThread` (None: published by the diagram)."""
    builder = DiagramBuilder()
    station = builder.AddSystem(
        MakeSimStation(scenario, patient=patient, name="station", slice_frames=False)
    )
    tau = station.GetOutputPort("tau_external")
    if undeclared_load:
        weight = builder.AddNamedSystem("probe_weight", ProbeWeightTorque(scenario))
        builder.Connect(
            station.GetOutputPort("joint_position"), weight.GetInputPort("joint_position")
        )
        builder.Connect(tau, weight.GetInputPort("tau_external"))
        tau = weight.GetOutputPort("tau_external")
    wire = AddSimulatedDriverWire(
        builder,
        lcm,
        position=station.GetOutputPort("joint_position"),
        velocity=station.GetOutputPort("joint_velocity"),
        tau_external_drake=tau,
        rate_hz=rate_hz,
        command_expiry=expire_sec,
        command_latency=faults.command_latency,
        status_drop_probability=faults.status_drop,
        seed=seed,
        command_channel=command_channel,
        status_channel=status_channel,
        status_sink=status_sink,
    )
    builder.Connect(wire.velocity, station.GetInputPort("joint_velocity_command"))
    diagram = builder.Build()
    diagram.set_name("rehearsal_sim")
    return diagram, station, wire


@dataclasses.dataclass
class RunStats:
    """Timing of a paced run: simulated s, wall s, busy s (wall time stepping, excluding
    sleeps), CPU s of the process (all threads: video server, wire tap), largest lag behind
    the wall clock (s), ticks, ticks late (more than one tick behind). ``margin``: simulated
    s per busy s, how many times real time the simulation ran when it ran (on a loaded
    machine this includes waiting for a core); ``cpu_margin``: simulated s per CPU s, the
    same with a core to itself."""

    sim_s: float = 0.0
    wall_s: float = 0.0
    busy_s: float = 0.0
    cpu_s: float = 0.0
    max_lag_s: float = 0.0
    ticks: int = 0
    late_ticks: int = 0
    # Per tick: wall s of its step (compute), how late it started (lag), and what it held:
    # "frame" (a picture's pose snapshot taken), "plant" (a plant step), "wire" (neither).
    compute: list = dataclasses.field(default_factory=list, repr=False)
    lag: list = dataclasses.field(default_factory=list, repr=False)
    kinds: list = dataclasses.field(default_factory=list, repr=False)
    period: float = math.nan
    # Garbage collections during the run: (generation, pause s), and their (start, end)
    # (monotonic s).
    gc_pauses: list = dataclasses.field(default_factory=list, repr=False)
    gc_spans: list = dataclasses.field(default_factory=list, repr=False)
    # Per tick: when its step started (monotonic s).
    starts: list = dataclasses.field(default_factory=list, repr=False)

    def spans(self, kind: str) -> list:
        """(start, end) (monotonic s) of the ticks that held ``kind``."""
        return [(s, s + c) for s, c, k in zip(self.starts, self.compute, self.kinds) if k == kind]

    def as_dict(self) -> dict:
        d = {
            k: v
            for k, v in dataclasses.asdict(self).items()
            if k not in ("compute", "lag", "kinds", "gc_pauses", "gc_spans", "starts")
        }
        d["margin"] = self.sim_s / self.busy_s if self.busy_s > 0 else None
        d["cpu_margin"] = self.sim_s / self.cpu_s if self.cpu_s > 0 else None
        if self.compute:
            d["loop"] = loop_statistics(self.period, self.compute, self.lag)
            # Where the time goes: compute (ms) of the ticks by what they held.
            compute, kinds = np.asarray(self.compute), np.asarray(self.kinds)
            d["loop"]["compute_by_kind_ms"] = {
                kind: percentiles_ms(compute[kinds == kind]) for kind in ("frame", "plant", "wire")
            }
        d["gc"] = gc_statistics(self.gc_pauses)
        return d


class RehearsalSim:
    """Runs a :func:`BuildRehearsalSim` diagram at real time and watches it.

    Before the first command arrives the robot rests where the operator placed it: the
    simulation holds (statuses and the first picture keep coming) so that it costs nothing
    while the scan side starts; from the first command on it steps in ticks of
    1 / ``rate_hz`` s paced to the wall clock. Records the applied command and joint speeds
    per tick, the true contact force peak and the PIVOT-like motion (for drills).

    ``on_pose(snapshot)``: at the first tick and every ``frame_period`` s of simulated time
    after it, the :class:`~drake_rus.rehearsal.video_process.PoseSnapshot` a picture is
    rendered from (the probe pose and the label volume's pose at the end of that tick,
    stamped with the wall clock then); it must return at once (e.g. a pipe write)."""

    def __init__(
        self,
        diagram,
        station,
        wire,
        lcm,
        *,
        rate_hz: float,
        frame_period: float,
        command_channel: str = "PANDA_COMMAND",
        lcm_url: str | None = None,
        status_thread: StatusPublisherThread | None = None,
        plant_period: float | None = None,
        on_pose: Callable[[PoseSnapshot], None] | None = None,
    ):
        self.diagram, self.station, self.wire, self.lcm = diagram, station, wire, lcm
        self._on_pose = on_pose
        self.frames = 0  # pose snapshots handed to on_pose
        self._next_frame = -math.inf  # simulated time (s) of the next snapshot
        self.status_thread = status_thread
        self.plant_period = plant_period
        self.period = 1.0 / float(rate_hz)
        self.frame_period = float(frame_period)
        self.simulator = Simulator(diagram)
        self.context = self.simulator.get_mutable_context()
        self.station_context = station.GetMyContextFromRoot(self.context)
        self.first_command_wall: float | None = None
        self.t_first_command: float | None = None  # simulated time then (s)
        self.arrivals: list[tuple] = []
        import drake

        self._command_type = drake.lcmt_panda_command
        # Every command with its arrival time: a wire tap on udpm://, else a subscription.
        self.tap = None
        if lcm_url is not None and lcm_url.startswith("udpm://"):
            self.tap = LcmUdpmTap(
                lcm_url,
                command_channel,
                on_packet=lambda t, sender, seq, data: self._on_command(data, t, sender, seq),
            )
        else:
            self.lcm.Subscribe(command_channel, self._on_command)
        self.stats = RunStats()
        self.speeds: list[tuple[float, float, float]] = []  # wall, max|v|, max|v cmd|
        self.force_peak = 0.0
        self.force_peak_time = math.nan
        self.pivot = PivotDetector()
        self.pivot_like_s = 0.0
        self.force_now = 0.0
        # Per truth sample: sim time s, tip speed m/s, turn rate rad/s, true force N,
        # PIVOT-like s.
        self.motion: list[tuple] = []
        self.simulator.Initialize()
        self._sensor = (
            station.GetSubsystemByName("slice_sensor")
            if station.HasSubsystemNamed("slice_sensor")
            else None
        )
        self._publisher = wire.publisher

    def _on_command(
        self, data: bytes, now: float | None = None, sender: str = "", seq: int = -1
    ) -> None:
        """Every command as it arrives (before the driver's subscriber keeps only the
        newest): wall time s, utime us, max |v| rad/s, sender, LCM sequence number."""
        now = time.time() if now is None else now
        try:
            msg = self._command_type.decode(data)
        except Exception:  # not a panda command: the driver would ignore it too
            return
        vmax = max((abs(v) for v in msg.joint_velocity), default=0.0)
        self.arrivals.append((now, int(msg.utime), float(vmax), sender, int(seq)))
        if self.first_command_wall is None:
            self.first_command_wall = now

    def _port(self, name):
        return self.station.GetOutputPort(name).Eval(self.station_context)

    def prime(self) -> None:
        """The first picture's pose (the robot at rest where the operator placed it) and
        the first status; starts the status thread."""
        self.snapshot()
        if self.status_thread is not None:
            self._publisher.ForcedPublish(self._publisher.GetMyContextFromRoot(self.context))
            self.status_thread.start()

    def snapshot(self) -> PoseSnapshot | None:
        """Hands the pose now to ``on_pose`` (None without one or without a patient's label
        volume) and schedules the next one a frame period later."""
        t = self.context.get_time()
        self._next_frame = t + self.frame_period
        if self._on_pose is None or self._sensor is None:
            return None
        sensor_context = self._sensor.GetMyContextFromRoot(self.context)
        snap = PoseSnapshot(
            frame_index=self.frames,
            t=t,
            stamp=time.time(),
            X_BP=np.asarray(self._port("X_BP").GetAsMatrix4(), float),
            X_BV=np.asarray(self._sensor.volume_pose(sensor_context).GetAsMatrix4(), float),
        )
        self.frames += 1
        self._on_pose(snap)
        return snap

    def hold(self, should_stop: Callable[[], bool]) -> None:
        """Until the first command (or ``should_stop()``): a status every period, no
        stepping (the video output keeps showing the first picture)."""
        pub_context = self._publisher.GetMyContextFromRoot(self.context)
        while self.first_command_wall is None and not should_stop():
            if self.status_thread is None:
                self._publisher.ForcedPublish(pub_context)
            self._wait(self.period)

    def observe(self, truth: bool = True) -> None:
        """Per tick: joint speeds and the applied command; with ``truth``, also the true
        contact force (its peak) and PIVOT-like motion."""
        v = np.asarray(self._port("joint_velocity"))
        v_cmd = np.asarray(
            self.wire.velocity.Eval(self.wire.receiver.GetMyContextFromRoot(self.context))
        )
        self.speeds.append((time.time(), float(np.abs(v).max()), float(np.abs(v_cmd).max())))
        if not truth:
            return
        force = contact_force_along_approach(self._port("probe_contact_wrench_true"))
        if force > self.force_peak:
            self.force_peak, self.force_peak_time = force, self.context.get_time()
        self.pivot_like_s = self.pivot.update(self.context.get_time(), self._port("X_BP"), force)
        self.force_now = force
        self.motion.append(
            (
                self.context.get_time(),
                self.pivot.tip_speed,
                self.pivot.turn_rate,
                force,
                self.pivot_like_s,
            )
        )

    def run(
        self,
        should_stop: Callable[[], bool],
        every: Callable | None = None,
        every_period: float = 0.2,
        truth_every: int = 4,
    ) -> RunStats:
        """Steps at real time from the first command until ``should_stop()``; observes
        the truth every ``truth_every`` ticks; calls ``every()`` about every
        ``every_period`` s of wall time."""
        st = self.stats
        st.period = self.period
        t_sim0 = self.context.get_time()
        self.t_first_command = t_sim0
        wall0 = time.monotonic()
        cpu0 = time.process_time()
        next_every = wall0
        k = 0
        with GcPauses(st.gc_pauses, st.gc_spans):
            while not should_stop():
                # Tick k covers (t_{k-1}, t_k]; it is due when the wall clock reaches t_{k-1}.
                start = time.monotonic()
                st.starts.append(start)
                st.lag.append(max(0.0, (start - wall0) - k * self.period))
                k += 1
                target = t_sim0 + k * self.period
                t_start = self.context.get_time()
                self.simulator.AdvanceTo(target)
                self.observe(truth=k % truth_every == 0)
                framed = target >= self._next_frame - 1e-9
                if framed:
                    self.snapshot()
                now = time.monotonic()
                st.compute.append(now - start)
                st.kinds.append("frame" if framed else self._kind(t_start))
                st.busy_s += now - start
                st.ticks += 1
                lag = (now - wall0) - (target - t_sim0)
                if lag > self.period:
                    st.late_ticks += 1
                st.max_lag_s = max(st.max_lag_s, lag)
                if every is not None and now >= next_every:
                    every()
                    next_every = now + every_period
                if lag < 0.0:
                    self._wait(-lag)
        st.sim_s = self.context.get_time() - t_sim0
        st.wall_s = time.monotonic() - wall0
        st.cpu_s = time.process_time() - cpu0
        return st

    def _kind(self, t_start: float) -> str:
        """What the tick from ``t_start`` held (its updates are those at ``t_start``): a
        plant step, else only the wire. (A tick that took a pose snapshot is "frame".)"""
        period = self.plant_period
        at = bool(period) and abs(t_start / period - round(t_start / period)) < 1e-6
        return "plant" if at else "wire"

    def _wait(self, seconds: float) -> None:
        """Sleeps ``seconds`` with the interpreter lock released (the statuses go out
        meanwhile), handling arriving messages every ``WAIT_POLL`` s (the diagram's
        subscriber latches the newest at the next step). The subscription holds one
        pending message and LCM drops what arrives while it is full, so it is drained at
        once, tap or not: waiting for the next tick lost a stop command that followed a
        moving one within the tick (the robot then ran on the moving one until the
        driver's expiry). With a wire tap every arrival is also recorded, exactly, by the
        tap's thread. Never a blocking ``HandleSubscriptions(timeout)``: DrakeLcm holds the
        interpreter lock while it waits, and every other thread of the process with it."""
        end = time.monotonic() + seconds
        while True:
            self.lcm.HandleSubscriptions(0)
            remaining = end - time.monotonic()
            if remaining <= 0.0:
                return
            time.sleep(min(remaining, WAIT_POLL))

    def close(self) -> None:
        if self.tap is not None:
            self.tap.close()
        if self.status_thread is not None:
            self.status_thread.close()

    def kidney_pose(self) -> RigidTransform:
        return self._port("X_BK_true")

    def joint_velocity(self) -> np.ndarray:
        return np.asarray(self._port("joint_velocity"), float).copy()

    def applied_command(self) -> np.ndarray:
        return np.asarray(
            self.wire.velocity.Eval(self.wire.receiver.GetMyContextFromRoot(self.context)), float
        ).copy()
