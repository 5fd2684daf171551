"""Issue 17: small usability rules: hardware rates, OSError messages, scheduler addresses."""

import errno
import logging
from types import SimpleNamespace

import pytest

from drake_rus.cli import UserError, check_arguments, check_scheduler
from drake_rus.io_utils import describe_os_error
from drake_rus.scenario import ApplyOverrides, LoadScenario


def test_default_scenario_has_no_rate_warning(caplog):
    from drake_rus.hardware.station import _check_rates

    with caplog.at_level(logging.WARNING):
        _check_rates(LoadScenario(scenario_name="hardware"))
        _check_rates(LoadScenario())
    assert "command_rate_hz" not in caplog.text


def test_odd_command_rate_still_warns(caplog):
    from drake_rus.hardware.station import _check_rates

    scenario = ApplyOverrides(LoadScenario(), "{hardware_interface: {command_rate_hz: 150}}")
    with caplog.at_level(logging.WARNING):
        _check_rates(scenario)
    assert "command_rate_hz" in caplog.text


def test_os_error_message_names_the_argument(tmp_path):
    args = SimpleNamespace(command="scan", out=str(tmp_path / "o"), record=None)
    e = OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "o" / "a.png"))
    assert describe_os_error(e, args).startswith("--out: no space left")
    e = OSError(errno.EACCES, "Permission denied", "/elsewhere/x")
    assert describe_os_error(e, args) == "cannot write /elsewhere/x (Permission denied)"


@pytest.mark.parametrize("address", ["nohost", "http://h:1", "tcp://:80", "tcp://h:port"])
def test_scheduler_address_form(address):
    with pytest.raises(UserError, match="--scheduler"):
        check_scheduler(address, timeout=0.5)


@pytest.mark.parametrize(
    "name,value",
    [
        ("views", -2),
        ("starts", 0),
        ("depth", -1),
        ("voxel_mm", 0.0),
        ("voxel_mm", float("nan")),
        ("voxel", 0.5),
        ("max_sim_time", float("inf")),
        ("duration", 0.0),
        ("workers", -1),
        ("runs", 0),
        ("count", 0),
        ("n", 0),
        ("seed", -5),
    ],
)
def test_argument_rules_name_the_flag(name, value):
    with pytest.raises(UserError, match="--" + name.replace("_", "-")):
        check_arguments(SimpleNamespace(**{name: value}))


def test_argument_rules_accept_the_defaults():
    check_arguments(
        SimpleNamespace(
            views=3,
            starts=5,
            depth=1,
            voxel_mm=1.0,
            voxel=0.002,
            max_sim_time=150.0,
            duration=6.0,
            workers=2,
            runs=1,
            count=None,
            n=20,
            seed=0,
        )
    )
