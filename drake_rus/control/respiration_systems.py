"""The respiration LeafSystems of the scan, thin over ``control.respiration``:

- :class:`RespirationEstimator`: the patient's respiratory state from the probe's pose and
  contact force (what any station has);
- :class:`BreathHoldProtocol`: the breath-hold protocol or gated free breathing (the
  scenario's ``respiration.mode``): the supervisor's ``motion_allowed`` and what the
  patient is told;
- :class:`BreathPrompter`: says it (a console line; spoken where a speech synthesiser is
  installed).
"""

from __future__ import annotations

import math
import shutil
import subprocess
import sys

from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import EventStatus, LeafSystem

from drake_rus.control import respiration as R

__all__ = ["RespirationEstimator", "BreathHoldProtocol", "BreathPrompter", "speech_command"]

PROMPT_TEXT = {
    0: "",
    1: "breathe in ... and hold",
    2: "breathe out ... and hold",
    3: "breathe normally",
}


class RespirationEstimator(LeafSystem):
    """The respiratory state of the patient under the probe (``respiration_update``).

    Inputs: ``X_BP`` (RigidTransform: the probe tip in B), ``contact_force`` (1-vector, N,
    filtered, positive pressing), optional ``v_command`` (3-vector, m/s, in B: the tip
    velocity the scan commands across the beam) and ``omega_command`` (3-vector, rad/s, in
    B: the angular velocity it commands): the probe's own motion (``own_motion_speed``),
    unknown when unconnected. Outputs: ``respiration_state`` (1-vector: UNKNOWN 0,
    BREATHING 1, HOLDING 2, END_EXPIRATION 3), ``respiration_since`` (1-vector, s: when the
    current state began, estimated), ``probe_moving`` (1-vector 0/1: the probe taken as
    moving of its own accord, ``probe_moving``), ``respiration`` (abstract
    RespirationState, for logs). Updated every ``period`` s (the controller's)."""

    def __init__(self, config, desired_force: float, period: float):
        super().__init__()
        self._cfg = config
        self._contact = 0.5 * float(desired_force)
        self._X = self.DeclareAbstractInputPort("X_BP", AbstractValue.Make(RigidTransform()))
        self._F = self.DeclareVectorInputPort("contact_force", 1)
        self._v = self.DeclareVectorInputPort("v_command", 3)
        self._w = self.DeclareVectorInputPort("omega_command", 3)
        self._s = self.DeclareAbstractState(AbstractValue.Make(R.RespirationState()))
        self.DeclarePeriodicUnrestrictedUpdateEvent(period, 0.0, self._update)
        ticket = {self.abstract_state_ticket(self._s)}
        self.DeclareVectorOutputPort(
            "respiration_state",
            1,
            lambda c, o: o.SetAtIndex(0, float(self.state(c).state)),
            prerequisites_of_calc=ticket,
        )
        self.DeclareVectorOutputPort(
            "respiration_since",
            1,
            lambda c, o: o.SetAtIndex(0, self.state(c).since),
            prerequisites_of_calc=ticket,
        )
        self.DeclareVectorOutputPort(
            "probe_moving",
            1,
            lambda c, o: o.SetAtIndex(0, float(R.probe_moving(self.state(c)))),
            prerequisites_of_calc=ticket,
        )
        self.DeclareAbstractOutputPort(
            "respiration",
            lambda: AbstractValue.Make(R.RespirationState()),
            lambda c, o: o.set_value(self.state(c)),
            prerequisites_of_calc=ticket,
        )

    def state(self, context) -> R.RespirationState:
        return context.get_abstract_state(self._s).get_value()

    def _update(self, context, state):
        X = self._X.Eval(context)
        F = float(self._F.Eval(context)[0])
        own = math.nan
        if self._v.HasValue(context) and self._w.HasValue(context):
            own = R.own_motion_speed(self._v.Eval(context), self._w.Eval(context))
        new = R.respiration_update(
            self.state(context),
            context.get_time(),
            X.translation(),
            X.rotation().matrix()[:, 2],
            F,
            math.isfinite(F) and F > self._contact,
            self._cfg,
            own,
        )
        state.get_mutable_abstract_state(self._s).set_value(new)


class BreathHoldProtocol(LeafSystem):
    """``respiration.mode`` on top of the estimator: ``protocol_step`` (breath_hold) or
    ``gate_step`` (gated).

    Inputs: ``phase`` (1-vector, the supervisor's), ``localization_ready`` (1-vector, 0/1),
    ``respiration_state`` and ``respiration_since`` (1-vectors, the estimator's). Outputs:
    ``motion_allowed`` (1-vector 0/1: the supervisor's), ``breath_prompt`` (1-vector,
    motion.Prompt: what the patient is told), ``breathing_error`` (abstract str: why the
    scan must stop, "" while it may go on), ``protocol`` (abstract ProtocolState)."""

    def __init__(self, config, period: float):
        super().__init__()
        self._cfg = config
        self._phase = self.DeclareVectorInputPort("phase", 1)
        self._ready = self.DeclareVectorInputPort("localization_ready", 1)
        self._resp = self.DeclareVectorInputPort("respiration_state", 1)
        self._since = self.DeclareVectorInputPort("respiration_since", 1)
        self._s = self.DeclareAbstractState(AbstractValue.Make(R.ProtocolState()))
        self.DeclarePeriodicUnrestrictedUpdateEvent(period, 0.0, self._update)
        ticket = {self.abstract_state_ticket(self._s)}
        self.DeclareVectorOutputPort(
            "motion_allowed",
            1,
            lambda c, o: o.SetAtIndex(0, float(self.state(c).allowed)),
            prerequisites_of_calc=ticket,
        )
        self.DeclareVectorOutputPort(
            "breath_prompt",
            1,
            lambda c, o: o.SetAtIndex(0, float(self.state(c).prompt)),
            prerequisites_of_calc=ticket,
        )
        self.DeclareAbstractOutputPort(
            "breathing_error",
            lambda: AbstractValue.Make(""),
            lambda c, o: o.set_value(self.state(c).error),
            prerequisites_of_calc=ticket,
        )
        self.DeclareAbstractOutputPort(
            "protocol",
            lambda: AbstractValue.Make(R.ProtocolState()),
            lambda c, o: o.set_value(self.state(c)),
            prerequisites_of_calc=ticket,
        )

    def state(self, context) -> R.ProtocolState:
        return context.get_abstract_state(self._s).get_value()

    def _update(self, context, state):
        phase = int(round(self._phase.Eval(context)[0]))
        resp = int(round(self._resp.Eval(context)[0]))
        s = self.state(context)
        if self._cfg.mode == "gated":
            allowed = R.gate_step(phase, resp)
            if allowed == s.allowed:
                return EventStatus.DidNothing()
            new = R.ProtocolState(allowed=allowed, prompts=s.prompts)
        else:
            ready = self._ready.HasValue(context) and self._ready.Eval(context)[0] > 0.5
            new = R.protocol_step(
                s,
                context.get_time(),
                phase,
                ready,
                resp,
                float(self._since.Eval(context)[0]),
                self._cfg,
            )
        state.get_mutable_abstract_state(self._s).set_value(new)
        return EventStatus.Succeeded()


def speech_command(text: str) -> list[str] | None:
    """The command that speaks ``text`` with an installed speech synthesiser (espeak-ng,
    espeak), or None: speech is never required."""
    for name in ("espeak-ng", "espeak"):
        path = shutil.which(name)
        if path:
            return [path, text]
    return None


class BreathPrompter(LeafSystem):
    """Tells the operator and the patient each new prompt: a console line
    "scan: [patient] breathe in ... and hold (t s)" on ``stream``, and, with ``speak``, the
    words through a speech synthesiser if one is installed (started in the background; a
    missing or failing one only loses the voice). Input ``breath_prompt`` (1-vector,
    motion.Prompt). Publishes at ``period``. ``said``: the prompts given ((time s, text),
    ...)."""

    def __init__(self, period: float, *, speak: bool = False, stream=None):
        super().__init__()
        self._prompt = self.DeclareVectorInputPort("breath_prompt", 1)
        self._speak = speak
        self._stream = stream
        self._last = 0
        self.said: list = []
        self.DeclarePeriodicPublishEvent(period, 0.0, self._publish)

    def _publish(self, context):
        prompt = int(round(self._prompt.Eval(context)[0]))
        if prompt == self._last:
            return EventStatus.DidNothing()
        self._last = prompt
        text = PROMPT_TEXT.get(prompt, "")
        if not text:
            return EventStatus.DidNothing()
        t = context.get_time()
        self.said.append((t, text))
        stream = self._stream if self._stream is not None else sys.stderr
        print(f"scan: [patient] {text} ({t:.1f} s)", file=stream, flush=True)
        if self._speak:
            command = speech_command(text)
            if command is not None:
                try:
                    subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                except OSError:
                    pass
        return EventStatus.Succeeded()
