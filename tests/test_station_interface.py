"""The station interface is the one list of ports: both stations match it, the docs' table
is generated from it, and a station that strays from it is refused."""

import numpy as np
import pytest
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, PassThrough

from drake_rus.anatomy import load_patient
from drake_rus.paths import REPO_ROOT
from drake_rus.scenario import LoadScenario
from drake_rus.station_interface import (
    ROBOT_SENSOR_PORTS,
    STATION_PORTS,
    CheckStationPorts,
    StationInterfaceError,
    port,
    ports_of,
    update_port_table,
)
from drake_rus.stations import MakeStation


def test_docs_port_table_is_generated_from_the_interface():
    text = (REPO_ROOT / "docs" / "design.md").read_text()
    assert update_port_table(text) == text, (
        "docs/design.md's port table is stale: run "
        "`python -m drake_rus.station_interface --update docs/design.md`"
    )


def test_sim_station_matches_the_interface_with_and_without_a_patient():
    scenario = LoadScenario()
    CheckStationPorts(MakeStation(scenario), "sim")  # placeholder torso
    patient = load_patient("test:0", voxel_size=0.004, progress=False)
    station = MakeStation(scenario, patient=patient)
    CheckStationPorts(station, "sim")
    assert station.HasOutputPort("us_image") and station.HasOutputPort("X_BK_true")


def _fake_station(names_sizes, inputs=(("joint_velocity_command", 7),)):
    builder = DiagramBuilder()
    for name, size in inputs:
        p = builder.AddNamedSystem(f"in_{name}", PassThrough(size))
        builder.ExportInput(p.get_input_port(), name)
    for name, size in names_sizes:
        src = builder.AddNamedSystem(name, ConstantVectorSource(np.zeros(size)))
        builder.ExportOutput(src.get_output_port(), name)
    diagram = builder.Build()
    diagram.set_name("fake")
    return diagram


def test_a_station_that_strays_is_refused_naming_each_difference():
    station = _fake_station(
        [("joint_position", 7), ("joint_velocity", 6), ("X_BP", 3), ("surprise", 1)]
    )
    with pytest.raises(StationInterfaceError) as e:
        CheckStationPorts(station, "hardware")
    text = str(e.value)
    assert "missing output port 'probe_force'" in text
    assert "'joint_velocity' has size 6, the interface says 7" in text
    assert "'X_BP' is a vector, the interface says abstract RigidTransform" in text
    assert "'surprise' is not a hardware station port" in text


def test_interface_lists():
    assert ROBOT_SENSOR_PORTS == ("joint_position", "joint_velocity", "X_BP", "probe_force")
    assert {p.name for p in ports_of("hardware")} >= {"commanded_velocity", "robot_ok"}
    assert "X_BK_true" not in {p.name for p in ports_of("hardware")}
    assert port("us_image").optional_on("sim") and not port("us_image").optional_on("hardware")
    assert len({p.name for p in STATION_PORTS}) == len(STATION_PORTS)
    with pytest.raises(KeyError, match="not a station port"):
        port("nope")
