"""The provenance record: enough to repeat a run (scenario as resolved, seeds, versions)."""

import platform

import yaml

from drake_rus.provenance import Provenance, cpu_model, package_versions, project_commit
from drake_rus.scenario import LoadScenario, Scenario


def test_record_holds_the_resolved_scenario_and_seeds():
    scenario = LoadScenario(
        scenario_name="default", scenario_text="{controller: {scan_speed: 0.004}, random_seed: 7}"
    )
    record = Provenance(
        scenario,
        scenario_name="default",
        overrides="{controller: {scan_speed: 0.004}, random_seed: 7}",
        seeds={"patient": "test:0"},
        argv=["drake-rus", "scan"],
    )
    assert record["seeds"] == {"patient": "test:0", "random_seed": 7}
    assert record["argv"] == ["drake-rus", "scan"]
    assert record["overrides"].startswith("{controller")
    resolved = yaml.safe_load(record["scenario_yaml"].replace("!Rpy", ""))
    assert resolved["controller"]["scan_speed"] == 0.004
    assert resolved["random_seed"] == 7
    assert record["packages"]["drake"] is not None
    assert record["packages"]["numpy"] is not None


def test_versions_name_missing_packages_as_none():
    assert package_versions(("no-such-package-drake-rus",))["no-such-package-drake-rus"] is None


def test_commit_is_a_sha_or_none():
    c = project_commit()
    assert c["commit"] is None or (len(c["commit"]) == 40 and int(c["commit"], 16) >= 0)
    assert Provenance(Scenario())["seeds"]["random_seed"] == 0


def test_cpu_model_from_cpuinfo(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: X\nmodel name\t: Example CPU @ 2.0GHz\n")
    assert cpu_model(str(info)) == "Example CPU @ 2.0GHz"
    # Without a readable model name: platform's answer, or None; never an exception.
    assert cpu_model(str(tmp_path / "missing")) in (None, platform.processor())
    assert "cpu" in Provenance()
