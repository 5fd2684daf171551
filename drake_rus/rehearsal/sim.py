"""The simulated side of a rehearsal: the virtual patient's station behind drake-franka-driver's
wire, with the ultrasound machine's video output.

:func:`BuildRehearsalSim` puts the simulated station (``drake_rus.station.MakeSimStation``:
FR3 + probe + soft patient, slice sensor and ultrasound emulator) behind
:func:`drake_rus.hardware.lcm_sim_driver.AddSimulatedDriverWire` (PANDA_COMMAND in, velocity
mode, the driver's command expiry; PANDA_STATUS out, wall-clock stamps, the driver's torque
sign) and taps the label frames at the imaging rate for a video output. :class:`RehearsalSim`
runs it paced at real time (:meth:`RehearsalSim.run`).

Only the physics steps in the simulation's own thread. What need not be there runs beside
it, so that the robot keeps its status rate: the statuses are published by
:class:`StatusPublisherThread` on its own wall-clock schedule (the newest state the
simulation handed it, stamped when sent), and the ultrasound pictures are emulated (the
station's own emulator model and seed: the same picture its ``us_image`` would give) and
JPEG-encoded by :class:`VideoWorker` (numba and OpenCV release the interpreter lock).

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
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem

from drake_rus.hardware.core import wall_clock_utime
from drake_rus.hardware.lcm_sim_driver import DRIVER_EXPIRE_SEC, AddSimulatedDriverWire
from drake_rus.hardware.systems import ProbeLoadTorque
from drake_rus.imaging.emulator import emulate
from drake_rus.imaging.frames import UsFrame
from drake_rus.rehearsal.core import PivotDetector
from drake_rus.rehearsal.wiretap import LcmUdpmTap
from drake_rus.robot import NUM_JOINTS, MakeControlPlant, contact_force_along_approach
from drake_rus.scan.pacing import GcPauses, gc_statistics, loop_statistics, percentiles_ms
from drake_rus.station import MakeSimStation

LOG = logging.getLogger("drake_rus.rehearsal")

__all__ = [
    "WireFaults",
    "BuildRehearsalSim",
    "RehearsalSim",
    "VideoTap",
    "VideoWorker",
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


class VideoTap(LeafSystem):
    """Input ``label_image`` (UsFrame of tissue labels). Every ``period`` s, hands each new
    frame and the wall-clock time (s) it was taken to ``on_frame(frame, wall_time)`` (the
    video output, which emulates it beside the simulation)."""

    def __init__(self, period: float, on_frame: Callable):
        super().__init__()
        self._on_frame = on_frame
        self._last = -1
        self.frames = 0
        self._in = self.DeclareAbstractInputPort(
            "label_image", AbstractValue.Make(UsFrame(np.zeros((1, 1), np.uint8)))
        )
        self.DeclarePeriodicPublishEvent(float(period), 0.0, self._publish)
        self.DeclareForcedPublishEvent(self._publish)

    def _publish(self, context):
        frame = self._in.Eval(context)
        if frame.valid and frame.frame_index != self._last:
            self._last = frame.frame_index
            self.frames += 1
            self._on_frame(frame, time.time())


class VideoWorker:
    """The ultrasound machine's picture pipeline beside the simulation: a thread emulates
    each label frame offered (``emulate(labels, model, seed, frame_index)``, the picture the
    station's ``us_image`` gives) and hands it to ``show(image, stamp)`` (the MJPEG output's
    push, which JPEG-encodes it). Only the newest frame waits; an older one waiting is
    dropped (``dropped``). ``close()`` stops it."""

    def __init__(self, model, seed: int, show: Callable):
        self._model, self._seed, self._show = model, int(seed), show
        self._cond = threading.Condition()
        self._waiting = None
        self._stop = False
        self.shown = 0
        self.dropped = 0
        self.busy: list[float] = []  # wall s per picture (emulation and encoding)
        self._thread = threading.Thread(target=self._run, name="drake_rus_video", daemon=True)
        self._thread.start()

    def offer(self, frame: UsFrame, stamp: float) -> None:
        with self._cond:
            if self._waiting is not None:
                self.dropped += 1
            self._waiting = (frame, stamp)
            self._cond.notify()

    def _run(self):
        while True:
            with self._cond:
                while self._waiting is None and not self._stop:
                    self._cond.wait(0.5)
                if self._stop:
                    return
                frame, stamp = self._waiting
                self._waiting = None
            start = time.perf_counter()
            try:
                image = emulate(frame.image, self._model, self._seed, frame.frame_index)
                self._show(image, stamp)
            except Exception as e:  # a picture lost must not stop the robot's simulation
                LOG.error("video: %s: %s", type(e).__name__, e)
            self.busy.append(time.perf_counter() - start)
            self.shown += 1

    def close(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join(2.0)


class StatusPublisherThread:
    """Publishes PANDA_STATUS on ``lcm`` every ``period`` s of the wall clock from its own
    thread: the newest status the simulation offered (``offer(msg)``), stamped with the
    wall clock when sent, each dropped with ``drop_probability`` (seeded by ``seed``). So
    the robot's status rate does not depend on how long a simulation step takes. Counts
    ``published`` and ``dropped``; ``times`` (monotonic s) of every status sent or
    dropped. ``start()``; ``close()``."""

    def __init__(
        self, lcm, channel: str, period: float, *, drop_probability: float = 0.0, seed: int = 0
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
    on_frame: Callable,
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
    already prepared for the scan's start (``drake_rus.scan.run.PrepareScenario``).
    ``on_frame(label_frame, wall_time)``: each new label frame (emulate it with the
    station's ``ultrasound_emulator``); ``status_sink(msg)``: each status, for a
    :class:`StatusPublisherThread` (None: published by the diagram)."""
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeSimStation(scenario, patient=patient, name="station"))
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
    tap = builder.AddNamedSystem(
        "video_tap", VideoTap(1.0 / scenario.imaging.frame_rate_hz, on_frame)
    )
    builder.Connect(station.GetOutputPort("label_image"), tap.get_input_port())
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
    # Per tick: wall s of its step (compute) and how late it started (lag).
    compute: list = dataclasses.field(default_factory=list, repr=False)
    lag: list = dataclasses.field(default_factory=list, repr=False)
    period: float = math.nan
    # Garbage collections during the run: (generation, pause s).
    gc_pauses: list = dataclasses.field(default_factory=list, repr=False)

    def as_dict(self) -> dict:
        d = {
            k: v
            for k, v in dataclasses.asdict(self).items()
            if k not in ("compute", "lag", "gc_pauses")
        }
        d["margin"] = self.sim_s / self.busy_s if self.busy_s > 0 else None
        d["cpu_margin"] = self.sim_s / self.cpu_s if self.cpu_s > 0 else None
        if self.compute:
            d["loop"] = loop_statistics(self.period, self.compute, self.lag)
        d["gc"] = gc_statistics(self.gc_pauses)
        return d


class RehearsalSim:
    """Runs a :func:`BuildRehearsalSim` diagram at real time and watches it.

    Before the first command arrives the robot rests where the operator placed it: the
    simulation holds (statuses and the first picture keep coming) so that it costs nothing
    while the scan side starts; from the first command on it steps in ticks of
    1 / ``rate_hz`` s paced to the wall clock. Records the applied command and joint speeds
    per tick, the true contact force peak and the PIVOT-like motion (for drills)."""

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
    ):
        self.diagram, self.station, self.wire, self.lcm = diagram, station, wire, lcm
        self.status_thread = status_thread
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
        self._tap = diagram.GetSubsystemByName("video_tap")
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

    def prime(self, max_time: float = 1.0) -> None:
        """Steps the resting robot until the first ultrasound picture exists (the imaging
        chain's first update), at most ``max_time`` s of simulated time."""
        tap_context = self._tap.GetMyContextFromRoot(self.context)
        while self._tap.frames == 0 and self.context.get_time() < max_time:
            self.simulator.AdvanceTo(self.context.get_time() + self.frame_period / 5)
            self._tap.ForcedPublish(tap_context)
        if self._tap.frames == 0:
            raise RuntimeError(
                f"the simulated station produced no ultrasound picture in "
                f"{max_time:g} s: does the patient have a label volume?"
            )
        if self.status_thread is not None:
            self._publisher.ForcedPublish(self._publisher.GetMyContextFromRoot(self.context))
            self.status_thread.start()

    def hold(self, should_stop: Callable[[], bool]) -> None:
        """Until the first command (or ``should_stop()``): a status every period, no
        stepping (the video output keeps showing the first picture)."""
        pub_context = self._publisher.GetMyContextFromRoot(self.context)
        while self.first_command_wall is None and not should_stop():
            if self.status_thread is None:
                self._publisher.ForcedPublish(pub_context)
            self.lcm.HandleSubscriptions(max(1, int(round(self.period * 1e3))))

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
        with GcPauses(st.gc_pauses):
            while not should_stop():
                # Tick k covers (t_{k-1}, t_k]; it is due when the wall clock reaches t_{k-1}.
                start = time.monotonic()
                st.lag.append(max(0.0, (start - wall0) - k * self.period))
                k += 1
                target = t_sim0 + k * self.period
                self.simulator.AdvanceTo(target)
                self.observe(truth=k % truth_every == 0)
                now = time.monotonic()
                st.compute.append(now - start)
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

    def _wait(self, seconds: float) -> None:
        """Sleeps ``seconds`` while handling arriving LCM messages at once (their arrival
        times stay exact; the diagram's subscriber latches them at the next step)."""
        end = time.monotonic() + seconds
        while True:
            remaining = end - time.monotonic()
            if remaining <= 0.0:
                return
            if remaining < 1e-3:
                time.sleep(remaining)
                return
            self.lcm.HandleSubscriptions(int(remaining * 1e3))

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
