"""How the UR driver names a stop when the controller refuses a command before its
published state shows why (the receive interface lags the control interface): the
dashboard's word wins, then the refusal itself."""

from __future__ import annotations

import pytest

from twinrl_robot.ur import driver
from twinrl_robot.ur.controller_link import ControllerHealth, controller_health
from twinrl_robot.ur.driver import RobotStopped, URArm
from twinrl_robot.ur.servo import ServoStream


class StaleReceive:
    """A receive interface whose last packet still shows a running program."""

    def isConnected(self) -> bool:
        return True

    def isEmergencyStopped(self) -> bool:
        return False

    def isProtectiveStopped(self) -> bool:
        return False

    def getRuntimeState(self) -> int:
        return 2


class LocalLink:
    """The controller link's health request, answered here from ``receive`` and ``stream``
    as the link's process answers it."""

    def __init__(self, receive: StaleReceive, stream: ServoStream) -> None:
        self.receive, self.stream = receive, stream

    def health(self) -> ControllerHealth:
        return controller_health(self.receive, self.stream)


def refused_arm(connection_failed: bool = False) -> URArm:
    arm = object.__new__(URArm)  # no controller: only the fault path is exercised
    arm.host, arm.fault = "192.0.2.1", None
    arm.stream = ServoStream(object(), 500.0)
    arm.stream.fault = "the controller refused a servo target: its program is not running"
    arm.stream.connection_failed = connection_failed
    arm._link = LocalLink(StaleReceive(), arm.stream)
    return arm


@pytest.mark.parametrize(
    ("dashboard", "named"),
    [
        ((False, "Safetystatus: NORMAL"), driver.LEFT_REMOTE),
        ((True, "Safetystatus: PROTECTIVE_STOP"), driver.PROTECTIVE_STOP),
        ((True, "Safetystatus: ROBOT_EMERGENCY_STOP"), driver.EMERGENCY_STOP),
        ((True, "Safetystatus: NORMAL"), "refused a servo target"),
        (None, "refused a servo target"),  # the dashboard does not answer
    ],
)
def test_a_refusal_is_named_by_the_dashboard_before_the_state_shows_it(
    monkeypatch, dashboard, named
) -> None:
    monkeypatch.setattr(driver, "_dashboard_status", lambda host: dashboard)
    arm = refused_arm()
    with pytest.raises(RobotStopped, match=named[:30]) as stopped:
        arm._check()
    assert "\n" not in str(stopped.value)
    with pytest.raises(RobotStopped, match=named[:30]):
        arm._check()  # the same fault until acknowledged


def test_a_failed_connection_is_not_asked_of_the_dashboard(monkeypatch) -> None:
    def unreachable(host: str) -> tuple[bool, str]:
        raise AssertionError("the dashboard was asked after the connection failed")

    monkeypatch.setattr(driver, "_dashboard_status", unreachable)
    arm = refused_arm(connection_failed=True)
    arm.stream.fault = "the connection to the controller failed (broken pipe)"
    with pytest.raises(RobotStopped, match="connection to the controller failed"):
        arm._check()


@pytest.mark.parametrize("ended_before_asked", [False, True])
def test_a_link_whose_process_dies_while_connecting_says_so_in_one_line(
    monkeypatch, ended_before_asked: bool
) -> None:
    import subprocess

    from twinrl_robot.ur import controller_link
    from twinrl_robot.ur.controller_link import ControllerLink, ControllerRefused

    monkeypatch.setattr(controller_link.sys, "executable", "/bin/false")  # exits at once
    if ended_before_asked:  # the child is gone before the host sends it the controller

        class EndsAtOnce(subprocess.Popen):
            def __init__(self, *args, **kwargs) -> None:
                super().__init__(*args, **kwargs)
                self.wait()

        monkeypatch.setattr(controller_link.subprocess, "Popen", EndsAtOnce)
    link = ControllerLink("192.0.2.1", 500.0)
    with pytest.raises(ControllerRefused, match="ended while connecting") as refused:
        link.open()
    assert "exit status 1" in str(refused.value) and "\n" not in str(refused.value)
    assert link.pid is None  # nothing left running


def test_a_receive_interface_that_is_not_connected_is_asked_nothing_more() -> None:
    class Disconnected(StaleReceive):
        def isConnected(self) -> bool:
            return False

        def getRuntimeState(self) -> int:
            raise AssertionError("a disconnected interface was asked for its program state")

    stream = ServoStream(object(), 500.0)
    assert not controller_health(Disconnected(), stream).connected
    arm = refused_arm()
    arm._link = LocalLink(Disconnected(), stream)
    with pytest.raises(RobotStopped, match="lost the connection to the controller"):
        arm._check()


def test_a_link_whose_process_has_ended_reports_a_lost_connection() -> None:
    from twinrl_robot.ur.controller_link import ControllerLink

    link = ControllerLink("192.0.2.1", 500.0)  # never opened: nothing to ask
    health = link.health()
    assert not health.connected and health.stream_connection_failed
    assert health.stream_fault == "the link to the controller is closed"
