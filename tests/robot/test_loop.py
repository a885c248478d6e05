"""The robot loop: one loop for every action source, recording through the Recorder."""

import numpy as np
import pytest

from tests.robot.test_wrappers import CONFIG, RealCell
from twinrl_data.mcap_log import read_episode
from twinrl_data.recorder import Recorder
from twinrl_data.session import Session
from twinrl_robot.backends import open_robot
from twinrl_robot.errors import PrivilegedStateError
from twinrl_robot.loop import JointCommand, privileged_success, run_episode
from twinrl_robot.scripted import ExpertSource
from twinrl_robot.wrappers import OperatorTakeover
from twinrl_sim.tasks import make_task


class Scripted:
    """Replays fixed actions; counts the times an operator interrupted it."""

    def __init__(self, actions):
        self.actions, self.interruptions = actions, 0

    def reset(self, task, config):
        self.t = 0

    def act(self, observation):
        self.t += 1
        return self.actions[self.t - 1]

    def interrupted(self):
        self.interruptions += 1


def test_the_expert_through_the_loop_is_recorded_step_for_step(tmp_path):
    task = make_task("pick_place")
    robot = open_robot("plant", task, seed=0, effort=True)
    recorder = Recorder(Session.create(tmp_path / "s"))
    meta = task.episode_meta(source="teleop", world=robot.world, names=robot.names, config=CONFIG)
    rng = np.random.default_rng(0)
    result = run_episode(
        robot,
        ExpertSource(rng, rng, 0.0),
        task,
        CONFIG,
        judge=privileged_success(robot),
        recorder=recorder,
        meta=meta,
    )
    assert result.success and 10 < result.steps < task.max_steps
    assert len(result.periods) == result.steps - 1 and min(result.periods) > 0
    episode = read_episode(result.path)
    assert len(episode) == result.steps and episode.meta.success
    assert episode.meta.fps == robot.control_hz and episode.meta.twin == task.scene.digest
    assert episode.data["next.done"][-1] and not episode.data["next.done"][:-1].any()
    assert set(episode.meta.names) >= {"observation.state", "observation.effort"}
    assert Session(tmp_path / "s").entries[0]["status"] == "complete"


def test_settle_steps_record_the_success_itself_with_the_arm_held(tmp_path):
    task = make_task("pick_place")
    robot = open_robot("plant", task, seed=0)
    recorder = Recorder(Session.create(tmp_path / "s"))
    meta = task.episode_meta(source="teleop", world=robot.world, names=robot.names, config=CONFIG)
    rng = np.random.default_rng(0)
    judged = []

    def judge(observation):  # sees the observation after each step
        judged.append(observation["observation.state"].copy())
        return robot.privileged.success

    result = run_episode(
        robot, ExpertSource(rng, rng, 0.0), task, CONFIG, judge=judge, recorder=recorder,
        meta=meta, settle=3,
    )  # fmt: skip
    episode = read_episode(result.path)
    assert result.success and len(episode) == result.steps + 3 == len(judged) + 3
    assert episode.data["next.success"][-4:].all() and not episode.data["next.success"][:-4].any()
    assert episode.data["next.done"][-1] and not episode.data["next.done"][:-1].any()
    held = episode.data["action"][-3:]
    assert not held[:, :6].any() and (held[:, 6] == episode.data["action"][-4, 6]).all()
    # the frame after the success step shows what the judge saw
    np.testing.assert_array_equal(episode.data["observation.state"][-3], judged[-1])


def test_interventions_reach_the_source_and_the_log(tmp_path):
    class Operator:
        judges_progress = False

        def reset(self, task, config):
            self.t = 0

        def intervene(self, observation, progress):
            self.t += 1
            return np.zeros(7, np.float32) if self.t in (3, 4) else None

    task = make_task("pick_place")
    robot = OperatorTakeover(open_robot("twin", task), Operator(), task)
    policy = np.tile(np.array([0.002, 0, 0, 0, 0, 0, 0], np.float32), (6, 1))
    source = Scripted(policy)
    recorder = Recorder(Session.create(tmp_path / "s"))
    meta = task.episode_meta(source="real_rl", world="twin", names=robot.names, config=CONFIG)
    result = run_episode(
        robot, source, task, CONFIG, judge=None, max_steps=6, recorder=recorder, meta=meta
    )
    assert result.interventions == 2 and source.interruptions == 2
    episode = read_episode(result.path)
    np.testing.assert_array_equal(episode.data["intervention"], [0, 0, 1, 1, 0, 0])
    assert episode.meta.num_interventions == 2
    # What the policy proposed is kept beside what the operator executed.
    np.testing.assert_array_equal(episode.data["action.policy"][2], policy[2])
    assert not episode.data["action"][2].any()
    assert (episode.data["next.reward"] == 0).all() and not episode.data["next.done"][:-1].any()


def test_joint_commands_are_servoed_and_their_motion_recorded(tmp_path):
    task = make_task("pick_place")
    robot = open_robot("twin", task)
    robot.reset(CONFIG)
    home = robot.observe()["observation.state"][:6].copy()
    targets = [home + 0.01 * (i + 1) for i in range(3)]
    motion = np.full(7, 0.001, np.float32)

    class Servo(Scripted):
        def act(self, observation):
            self.t += 1
            return JointCommand(targets[self.t - 1], 0.0, motion)

    recorder = Recorder(Session.create(tmp_path / "s"))
    meta = task.episode_meta(source="excitation", world="twin", names=robot.names)
    result = run_episode(
        robot, Servo([]), task, CONFIG, judge=None, max_steps=3, recorder=recorder, meta=meta
    )
    episode = read_episode(result.path)
    np.testing.assert_allclose(episode.data["command.joint_target"], targets, atol=1e-6)
    np.testing.assert_array_equal(episode.data["action"], [motion] * 3)


def test_a_real_cell_needs_a_judge_other_than_ground_truth(tmp_path):
    real = RealCell()
    with pytest.raises(PrivilegedStateError, match="judging success"):
        privileged_success(real)
    task = make_task("pick_place")
    source = Scripted([np.zeros(7, np.float32)] * 3)
    marks = iter([False, False, True])
    result = run_episode(real, source, task, CONFIG, judge=lambda _observation: next(marks))
    assert result.success and result.steps == 3 and result.path is None


def test_a_failing_step_closes_the_episode_it_recorded(tmp_path):
    task = make_task("pick_place")
    robot = open_robot("twin", task)
    source = Scripted([np.zeros(7, np.float32), np.zeros(5, np.float32)])  # malformed second
    session = Session.create(tmp_path / "s")
    meta = task.episode_meta(source="eval", world="twin", names=robot.names)
    with pytest.raises(ValueError, match="7 numbers"):
        run_episode(robot, source, task, CONFIG, judge=None, recorder=Recorder(session), meta=meta)
    entry = Session(tmp_path / "s").entries[0]
    assert entry["status"] == "complete" and entry["length"] == 1 and entry["success"] is False
    with pytest.raises(ValueError, match="both a recorder"):
        run_episode(robot, source, task, CONFIG, judge=None, recorder=Recorder(session))
