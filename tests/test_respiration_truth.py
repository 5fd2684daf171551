"""The scan copes with a breathing patient without reading the simulation's truth: built on
the simulated station (a patient who breathes and holds when told), no truth port of the
station feeds anything in the scan; and it runs on a station that has no truth ports at
all (the hardware station's interface)."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from drake_rus.scan.diagram import BuildScanDiagram
from drake_rus.scan.run import PrepareScenario
from drake_rus.scenario import LoadScenario
from drake_rus.station_interface import STATION_PORTS
from drake_rus.stations import MakeStation

TRUTH = {p.name for p in STATION_PORTS if p.group == "truth"}
BREATHING = (
    "{respiration: {mode: breath_hold}, patient: {motion: {breathing: {enabled: true, "
    "amplitude: 0.015, rate_per_min: 18}}}, imaging: {segmenter: classical}}"
)


@pytest.fixture(scope="module")
def setup():
    from drake_rus.anatomy import load_patient
    from drake_rus.localization.localize import load_registration_template

    scenario = LoadScenario(scenario_name="quick", scenario_text=BREATHING)
    patient = load_patient("test:0", progress=False)
    scenario, _, _ = PrepareScenario(scenario, patient)
    return scenario, patient, load_registration_template(scenario.localization.template)


def _without_truth(station):
    """The station re-exported without its truth ports (what the hardware station has, plus
    the patient's prompt input)."""
    builder = DiagramBuilder()
    builder.AddNamedSystem("inner", station)
    for i in range(station.num_input_ports()):
        port = station.get_input_port(i)
        builder.ExportInput(port, port.get_name())
    for i in range(station.num_output_ports()):
        port = station.get_output_port(i)
        if port.get_name() not in TRUTH:
            builder.ExportOutput(port, port.get_name())
    diagram = builder.Build()
    diagram.set_name("station")
    return diagram


def test_no_truth_port_feeds_the_scan(setup):
    scenario, patient, template = setup
    station = MakeStation(scenario, patient=patient)
    outputs = {station.get_output_port(i).get_name() for i in range(station.num_output_ports())}
    assert TRUTH & outputs
    builder, handles = BuildScanDiagram(scenario, station, template)
    assert handles.respiration is not None and handles.protocol is not None
    sources = {
        station.get_output_port(index).get_name()
        for (system, index) in builder.connection_map().values()
        if system is station
    }
    assert sources and not (sources & TRUTH), sources & TRUTH
    # The patient hears the scan: its prompt input is driven by the protocol.
    prompt = station.GetInputPort("breath_prompt")
    assert builder.connection_map()[(station, prompt.get_index())][0] is handles.protocol


def test_the_protocol_runs_on_a_station_without_truth_ports(setup):
    scenario, patient, template = setup
    station = _without_truth(MakeStation(scenario, patient=patient))
    names = {station.get_output_port(i).get_name() for i in range(station.num_output_ports())}
    assert not names & TRUTH
    builder, h = BuildScanDiagram(scenario, station, template)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    simulator.Initialize()
    simulator.AdvanceTo(3.0)
    context = simulator.get_context()
    phase = h.supervisor.GetOutputPort("phase").Eval(h.supervisor.GetMyContextFromRoot(context))
    assert int(phase[0]) == 1  # EXPLORE, waiting to ask for the first hold
    estimate = h.respiration.state(h.respiration.GetMyContextFromRoot(context))
    assert len(estimate.t) > 100 and np.all(np.isfinite(estimate.w))
