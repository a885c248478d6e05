"""Wrappers over a robot: each adds one behaviour and is tested alone; a real cell
(no privileged channel) is refused by whatever needs a simulation's ground truth."""

import numpy as np
import pytest

from twinrl_data.schema import EFFORT, ENVIRONMENT_STATE, STATE
from twinrl_robot.backends import open_robot
from twinrl_robot.errors import PrivilegedStateError
from twinrl_robot.operator import SimulatedOperator
from twinrl_robot.robot import Robot, Sent, require_privileged
from twinrl_robot.simulated import SimulatedCell
from twinrl_robot.wrappers import (
    GraspHold,
    NoiseLevels,
    OperatorTakeover,
    PrivilegedObservation,
    SafetyLimits,
    SensorNoise,
    layers,
    random_states,
    restore_random_states,
)
from twinrl_sim.control import action_bounds
from twinrl_sim.tasks import TaskConfig, make_task

CONFIG = TaskConfig(object=(0.45, -0.2, 0.3), target=(0.5, -0.08, 0.0))


class RealCell:
    """A robot as a real cell presents itself: sensors and an arm, no ground truth."""

    control_hz, world, privileged = 10.0, "real", None

    def __init__(self):
        self.names = {STATE: ["q.a", "qd.a", "tcp.x", "tcp.y", "tcp.z", "gripper.opening"]}
        self.sent: list[np.ndarray] = []
        self.holds = 0

    def reset(self, config):
        return self.observe()

    def observe(self):
        return {STATE: np.zeros(6, np.float32)}

    def act(self, action):
        self.sent.append(np.asarray(action))
        return Sent(action=np.asarray(action, np.float32), joint_target=np.zeros(6, np.float32))

    def hold(self):
        self.holds += 1

    def servo_joints(self, joint_target, gripper):
        return Sent(action=np.zeros(7, np.float32), joint_target=np.asarray(joint_target))

    def close(self):
        pass


def test_a_real_cell_is_a_robot_without_ground_truth():
    real = RealCell()
    assert isinstance(real, Robot) and isinstance(SafetyLimits(real), Robot)
    with pytest.raises(PrivilegedStateError, match="only a simulated cell"):
        require_privileged(real, "the simulated operator")
    with pytest.raises(PrivilegedStateError, match="object poses"):
        PrivilegedObservation(real)
    task = make_task("pick_place")
    with pytest.raises(PrivilegedStateError, match="the simulated operator"):
        OperatorTakeover(real, SimulatedOperator(), task)


def test_safety_limits_clip_every_action_and_reject_a_malformed_one():
    real = RealCell()
    safe = SafetyLimits(real)
    low, high = action_bounds()
    safe.act(np.array([1.0, -1.0, 0.0, 2.0, 0.0, -2.0, 3.0]))
    np.testing.assert_array_equal(real.sent[-1], [high[0], low[1], 0.0, high[3], 0.0, low[5], 1.0])
    inside = np.array([0.001, 0, 0, 0, 0, 0.01, 0.5], np.float32)
    safe.act(inside)
    np.testing.assert_array_equal(real.sent[-1], inside)
    with pytest.raises(ValueError, match="7 numbers"):
        safe.act(np.zeros(6))


def test_privileged_observation_adds_object_poses_with_their_names():
    cell = SimulatedCell(make_task("pick_place"))
    assert ENVIRONMENT_STATE not in cell.reset(CONFIG)
    seen = PrivilegedObservation(cell)
    obs = seen.reset(CONFIG)
    assert obs[ENVIRONMENT_STATE].shape == (len(seen.names[ENVIRONMENT_STATE]),)
    np.testing.assert_allclose(obs[ENVIRONMENT_STATE][:2], CONFIG.object[:2], atol=1e-6)


def test_sensor_noise_is_seeded_and_touches_only_sensors():
    cell = SimulatedCell(make_task("pick_place"), effort=True)
    exact = PrivilegedObservation(cell).reset(CONFIG)
    readings = []
    for _ in range(2):
        noisy = SensorNoise(PrivilegedObservation(cell), NoiseLevels(), seed=3)
        readings.append(noisy.reset(CONFIG))
    for key in (STATE, ENVIRONMENT_STATE, EFFORT):
        np.testing.assert_array_equal(readings[0][key], readings[1][key])
        assert not np.array_equal(readings[0][key], exact[key].astype(np.float32))
    # The gripper opening and the object orientations are read exactly.
    assert readings[0][STATE][-1] == np.float32(exact[STATE][-1])
    np.testing.assert_array_equal(
        readings[0][ENVIRONMENT_STATE][3:7], exact[ENVIRONMENT_STATE][3:7]
    )
    quiet = SensorNoise(cell, NoiseLevels(0, 0, 0, 0, 0), seed=3).reset(CONFIG)
    np.testing.assert_allclose(quiet[STATE], exact[STATE], atol=1e-6)


def test_grasp_hold_zeroes_the_arm_while_the_fingers_close():
    robot = GraspHold(open_robot("twin", "pick_place"))
    robot.reset(CONFIG)
    move_close = np.array([0.01, 0, 0, 0, 0, 0, 1.0], np.float32)
    executed = [robot.act(move_close).action for _ in range(2)]
    assert all(not a[:6].any() for a in executed)  # settle: the arm waits
    move_open = np.array([0.01, 0, 0, 0, 0, 0, 0.0], np.float32)
    assert robot.act(move_open).action[0] == pytest.approx(0.01)
    with pytest.raises(RuntimeError, match="reset"):
        GraspHold(RealCell()).act(move_open)


def test_operator_takeover_holds_the_arm_once_and_flags_its_steps():
    class TwoStepOperator:
        judges_progress = False

        def reset(self, task, config):
            self.step = 0

        def intervene(self, observation, progress):
            assert progress is None  # a teleop device is not told the ground truth
            self.step += 1
            return np.full(7, 0.5, np.float32) if self.step in (2, 3) else None

    real = RealCell()
    robot = OperatorTakeover(real, TwoStepOperator(), make_task("pick_place"))
    robot.reset(CONFIG)
    flags = [robot.act(np.zeros(7, np.float32)).intervention for _ in range(4)]
    assert flags == [False, True, True, False]
    assert real.holds == 1  # held where it was when the operator took the controls


def test_random_streams_of_a_stack_are_saved_and_restored():
    robot = open_robot("plant", "pick_place", seed=4)
    assert [type(layer).__name__ for layer in layers(robot)] == [
        "SafetyLimits",
        "SensorNoise",
        "PrivilegedObservation",
        "SimulatedCell",
    ]
    robot.reset(CONFIG)
    saved = random_states(robot)
    first = robot.observe()[STATE]
    restore_random_states(robot, saved)
    np.testing.assert_array_equal(robot.observe()[STATE], first)
    with pytest.raises(ValueError, match="do not match"):
        restore_random_states(open_robot("twin", "pick_place"), saved)


def test_backends_are_chosen_in_one_place():
    with pytest.raises(ValueError, match="unknown robot 'ur'"):
        open_robot("ur", "pick_place")
    with pytest.raises(ValueError, match="plant only"):
        open_robot("twin", "pick_place", effects={})
    twin = open_robot("twin", "pick_place", object_poses=False, cameras=("front",))
    obs = twin.reset(CONFIG)
    assert ENVIRONMENT_STATE not in obs and obs["observation.images.front"].ndim == 3
    assert twin.world == "twin" and open_robot("plant", "pick_place").world == "plant"
