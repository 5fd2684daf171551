"""The station interface: every port a station exports, written once.

Both stations (``drake_rus.station.MakeSimStation`` and
``drake_rus.hardware.station.MakeHardwareStation``) check themselves against
:data:`STATION_PORTS` when they are built (:func:`CheckStationPorts`); the tests, the fault
injection (``drake_rus.reliability``) and the port table of ``docs/design.md``
(:func:`port_table_markdown`, kept current by ``tests/test_station_interface.py``) read it
from here. The controller and the scan use only the ports both stations export.

    python -m drake_rus.station_interface            # print the port table (Markdown)
    python -m drake_rus.station_interface --update docs/design.md
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import sys
from pathlib import Path

from pydrake.systems.framework import PortDataType

__all__ = [
    "StationPort",
    "STATION_PORTS",
    "ports_of",
    "port",
    "ROBOT_SENSOR_PORTS",
    "CheckStationPorts",
    "StationInterfaceError",
    "port_table_markdown",
    "update_port_table",
]

SIM, HARDWARE = "sim", "hardware"


@dataclasses.dataclass(frozen=True)
class StationPort:
    """One exported port of a station.

    ``size``: the vector size, or None for an abstract port whose value is a ``value_type``
    (the class name). ``stations``: which stations export it; ``condition``: when a station
    exports it only in some configurations (then it is optional there). ``group``:
    ``command``, ``robot`` (what the robot senses; fault injection may corrupt these),
    ``imaging``, ``truth`` (simulation ground truth: never wired into a controller),
    ``patient`` (what the simulated patient hears) or ``hardware`` (the real robot's own
    status)."""

    name: str
    direction: str  # "in" or "out"
    size: int | None
    unit: str
    frame: str
    meaning: str
    group: str
    value_type: str = ""
    stations: tuple = (SIM, HARDWARE)
    condition: str = ""
    # The stations on which ``condition`` applies (default: every station exporting it).
    conditional_on: tuple | None = None

    def optional_on(self, station_kind: str) -> bool:
        """Whether a ``station_kind`` station may leave this port out (see ``condition``)."""
        where = self.stations if self.conditional_on is None else self.conditional_on
        return bool(self.condition) and station_kind in where

    def kind(self) -> str:
        """'vector 7' or 'abstract RigidTransform', as the table writes it."""
        return f"vector {self.size}" if self.size is not None else f"abstract {self.value_type}"


STATION_PORTS: tuple[StationPort, ...] = (
    StationPort(
        "joint_velocity_command",
        "in",
        7,
        "rad/s",
        "joints",
        "the FR3's joint-velocity mode",
        "command",
    ),
    StationPort("joint_position", "out", 7, "rad", "joints", "measured joints", "robot"),
    StationPort("joint_velocity", "out", 7, "rad/s", "joints", "measured joint rates", "robot"),
    StationPort(
        "X_BP",
        "out",
        None,
        "m",
        "P in B",
        "probe tip pose: forward kinematics of our FR3 model plus the scenario's probe calibration",
        "robot",
        value_type="RigidTransform",
    ),
    StationPort(
        "tau_external",
        "out",
        7,
        "N m",
        "joints",
        "external joint torques, Drake's sign: on the arm by the environment",
        "robot",
    ),
    StationPort(
        "probe_force",
        "out",
        6,
        "N m, N",
        "P, about P's origin",
        "[tau; f] on the probe by the environment, estimated from tau_external "
        "through the tip Jacobian (the same function in both stations)",
        "robot",
    ),
    StationPort(
        "us_image",
        "out",
        None,
        "grey levels, s",
        "image plane of P",
        "the ultrasound frame: uint8 image, capture time, the X_BP it was taken at, "
        "frame_index (-1: no frame yet)",
        "imaging",
        value_type="UsFrame",
        condition="the patient has a label volume (not the placeholder torso)",
        conditional_on=(SIM,),
    ),
    StationPort(
        "label_image",
        "out",
        None,
        "tissue labels",
        "image plane of P",
        "tissue labels of the same slice; read only by the oracle segmenter",
        "truth",
        value_type="UsFrame",
        stations=(SIM,),
        condition="the patient has a label volume",
    ),
    StationPort(
        "X_BK_true",
        "out",
        None,
        "m",
        "K in B",
        "the true canonical kidney frame, for metrics",
        "truth",
        value_type="RigidTransform",
        stations=(SIM,),
        condition="the patient has a label volume",
    ),
    StationPort(
        "probe_contact_wrench_true",
        "out",
        6,
        "N m, N",
        "P, about P's origin",
        "the plant's contact forces on the probe bodies",
        "truth",
        stations=(SIM,),
    ),
    StationPort(
        "contact_results",
        "out",
        None,
        "",
        "",
        "the plant's contact results",
        "truth",
        value_type="ContactResults",
        stations=(SIM,),
    ),
    StationPort(
        "plant_state",
        "out",
        -1,
        "m, rad, m/s, rad/s",
        "",
        "the whole plant state (its size depends on the patient's body)",
        "truth",
        stations=(SIM,),
    ),
    StationPort(
        "breath_hold",
        "out",
        1,
        "1",
        "",
        "1 while the simulated patient holds their breath",
        "truth",
        stations=(SIM,),
        condition="patient.motion.breathing.enabled",
    ),
    StationPort(
        "respiratory_level_true",
        "out",
        1,
        "1",
        "",
        "the simulated patient's respiratory level: 0 at end-expiration, 1 at a mean tidal "
        "inspiration",
        "truth",
        stations=(SIM,),
        condition="patient.motion.breathing.enabled",
    ),
    StationPort(
        "patient_offset_true",
        "out",
        3,
        "m",
        "B",
        "displacement of the simulated patient's anatomy (breathing and shift)",
        "truth",
        stations=(SIM,),
        condition="patient.motion (breathing or shift) enabled",
    ),
    StationPort(
        "breath_prompt",
        "in",
        1,
        "1",
        "",
        "what the scan tells the simulated patient (motion.Prompt: 0 nothing, 1 breathe in "
        "and hold, 2 breathe out and hold, 3 breathe normally); a real patient hears the "
        "operator or the spoken prompt",
        "patient",
        stations=(SIM,),
        condition="patient.motion.breathing.enabled",
    ),
    StationPort(
        "commanded_velocity",
        "out",
        7,
        "rad/s",
        "joints",
        "what was actually sent after the client-side guard",
        "hardware",
        stations=(HARDWARE,),
    ),
    StationPort(
        "robot_ok",
        "out",
        1,
        "1",
        "",
        "0 once the robot or its connection has failed",
        "hardware",
        stations=(HARDWARE,),
    ),
)

# What the robot senses, in the order the fault injection wraps them.
ROBOT_SENSOR_PORTS = tuple(
    p.name for p in STATION_PORTS if p.group == "robot" and p.name != "tau_external"
)


class StationInterfaceError(ValueError):
    """A station's ports differ from the interface; the message names each difference."""


def ports_of(station_kind: str, *, include_optional: bool = True) -> tuple[StationPort, ...]:
    """The ports a ``station_kind`` ('sim' or 'hardware') station exports."""
    if station_kind not in (SIM, HARDWARE):
        raise ValueError(f"station kind: expected 'sim' or 'hardware', got {station_kind!r}")
    return tuple(
        p
        for p in STATION_PORTS
        if station_kind in p.stations and (include_optional or not p.optional_on(station_kind))
    )


def port(name: str) -> StationPort:
    """The interface's entry for port ``name``."""
    for p in STATION_PORTS:
        if p.name == name:
            return p
    raise KeyError(
        f"'{name}' is not a station port; ports: {', '.join(p.name for p in STATION_PORTS)}"
    )


def _value_type_name(system_port) -> str:
    value = system_port.Allocate()
    try:
        return type(value.get_value()).__name__
    except (AttributeError, RuntimeError):
        return type(value).__name__


def CheckStationPorts(station, station_kind: str) -> None:
    """Raises :class:`StationInterfaceError` unless ``station`` (a built Diagram) exports
    exactly the interface's ports for ``station_kind``: every required port, no port the
    interface does not list for that station, and each with its size (vector) or value
    type (abstract)."""
    expected = {p.name: p for p in ports_of(station_kind)}
    found = {}
    for i in range(station.num_input_ports()):
        p = station.get_input_port(i)
        found[p.get_name()] = ("in", p)
    for i in range(station.num_output_ports()):
        p = station.get_output_port(i)
        found[p.get_name()] = ("out", p)
    problems = []
    for name, spec in expected.items():
        if name not in found:
            if not spec.optional_on(station_kind):
                problems.append(f"missing {spec.direction}put port '{name}'")
            continue
        direction, system_port = found[name]
        if direction != spec.direction:
            problems.append(f"'{name}' is an {direction}put, the interface says {spec.direction}")
            continue
        is_vector = system_port.get_data_type() == PortDataType.kVectorValued
        if spec.size is not None:
            if not is_vector:
                problems.append(f"'{name}' is abstract, the interface says {spec.kind()}")
            elif spec.size >= 0 and system_port.size() != spec.size:
                problems.append(
                    f"'{name}' has size {system_port.size()}, the interface says {spec.size}"
                )
        else:
            if is_vector:
                problems.append(f"'{name}' is a vector, the interface says {spec.kind()}")
            elif _value_type_name(system_port) != spec.value_type:
                problems.append(
                    f"'{name}' carries {_value_type_name(system_port)}, the "
                    f"interface says {spec.value_type}"
                )
    for name in found:
        if name not in expected:
            problems.append(
                f"'{name}' is not a {station_kind} station port of the interface "
                "(drake_rus/station_interface.py)"
            )
    if problems:
        raise StationInterfaceError(
            f"{station_kind} station '{station.get_name()}': " + "; ".join(problems)
        )


def _availability(p: StationPort) -> str:
    where = (
        "both"
        if set(p.stations) == {SIM, HARDWARE}
        else "sim only"
        if p.stations == (SIM,)
        else "hardware only"
    )
    if not p.condition:
        return where
    on = "" if p.conditional_on is None else f" ({', '.join(p.conditional_on)})"
    return f"{where}; when{on} {p.condition}"


def port_table_markdown() -> str:
    """The port table of docs/design.md, generated from :data:`STATION_PORTS`."""
    lines = [
        "| port | dir | type, size | unit | frame | stations | meaning |",
        "|---|---|---|---|---|---|---|",
    ]
    for p in STATION_PORTS:
        kind = "vector (plant size)" if p.size == -1 else p.kind()
        lines.append(
            f"| `{p.name}` | {p.direction} | {kind} | {p.unit or '-'} | "
            f"{p.frame or '-'} | {_availability(p)} | {p.meaning} |"
        )
    return "\n".join(lines) + "\n"


BEGIN, END = "<!-- station-ports:begin -->", "<!-- station-ports:end -->"


def update_port_table(text: str) -> str:
    """``text`` with the block between the station-ports markers replaced by the table."""
    pattern = re.compile(re.escape(BEGIN) + r".*?" + re.escape(END), re.S)
    if not pattern.search(text):
        raise ValueError(f"no {BEGIN} ... {END} block to update")
    return pattern.sub(lambda _: f"{BEGIN}\n{port_table_markdown()}{END}", text)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m drake_rus.station_interface", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--update", metavar="FILE", help="rewrite the table in FILE")
    args = parser.parse_args(argv)
    if args.update:
        path = Path(args.update)
        path.write_text(update_port_table(path.read_text()))
        print(f"updated {path}")
    else:
        sys.stdout.write(port_table_markdown())
    return 0


if __name__ == "__main__":
    sys.exit(main())
