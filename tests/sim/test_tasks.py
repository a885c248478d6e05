"""Tasks: configurations, regions, success, rewards and the scripted experts' success."""

import math

import numpy as np
import pytest

from tests.conftest import TASK_NAMES
from twinrl_robot.scripted import run_scripted_expert
from twinrl_sim.control import TRACKED_ROTATION
from twinrl_sim.env import TwinEnv
from twinrl_sim.planner import plan_demo
from twinrl_sim.tasks import TaskConfig, make_task, task_class
from twinrl_sim.tasks.expert import ObsView


@pytest.mark.parametrize("name", TASK_NAMES)
def test_regions_are_disjoint_and_sampled_configs_fall_in_them(name, rng):
    task = make_task(name)
    for region in ("ID", "OOD"):
        for _ in range(50):
            config = task.sample_config(rng, region)
            assert task.region_of(config) == region
            distance = np.hypot(
                config.object[0] - config.target[0], config.object[1] - config.target[1]
            )
            assert distance >= task.min_separation
    id_area, ood_area = task.regions["ID"], task.regions["OOD"]
    assert id_area.y[1] < ood_area.y[0] or ood_area.y[1] < id_area.y[0]


@pytest.mark.parametrize("name", TASK_NAMES)
def test_scripted_expert_solves_both_regions_of_the_twin(name):
    """>= 95 % per region on a modest sample (the benchmark runs more)."""
    report = run_scripted_expert(name, world="twin", episodes=20, seed=3)
    for region, rate in report.success_rate().items():
        assert rate >= 0.95, f"{name} {region}: {rate:.0%}"


@pytest.mark.parametrize("name", TASK_NAMES)
def test_a_fresh_episode_is_not_a_success_and_rewards_follow_the_paper(name):
    env = TwinEnv(name, reward="sparse")
    _, info = env.reset(seed=0)
    assert not info["success"]
    _, reward, terminated, truncated, _ = env.step(np.zeros(7, np.float32))
    assert reward == pytest.approx(-0.05) and not terminated and not truncated
    progress_terms = info["reward_terms"]
    assert set(progress_terms) == set(env.task.default_config()["dense_weights"])
    assert all(0.0 <= v <= 1.0 for v in progress_terms.values())


def test_configs_round_trip_and_bad_ones_are_explained():
    config = TaskConfig(object=(0.4, -0.2, 0.1), target=(0.5, -0.1, 0.0))
    assert TaskConfig.from_dict(config.to_dict()) == config
    with pytest.raises(ValueError, match="exactly the keys object and target"):
        TaskConfig.from_dict({"object": [0, 0, 0]})
    with pytest.raises(ValueError, match="three finite numbers"):
        TaskConfig.from_dict({"object": [0, 0], "target": [0, 0, 0]})
    with pytest.raises(ValueError, match="did you mean 'pick_place'"):
        task_class("pick_plac")
    with pytest.raises(ValueError, match="unknown region 'MID'"):
        make_task("pick_place").region("MID")


def _largest_turn_lead(env, config, act, steps: int) -> float:
    """Largest lead (degrees) of the commanded tool yaw (the sum of the actions' rz) over
    the measured one while ``act(obs, t)`` drives the arm."""
    obs, _ = env.reset(options={"config": config})
    commanded, lead = 0.0, 0.0
    for t in range(steps):
        action = act(obs, t)
        commanded += float(action[5])
        obs, *_ = env.step(action)
        lead = max(lead, abs(math.degrees(commanded - ObsView(env.task.scene, obs).tool_yaw)))
    return lead


def test_demonstrators_turn_no_faster_than_the_arm_follows():
    """A policy sees the measured pose only: demos whose command had run 50 degrees ahead
    of the arm taught it to stop turning while the tool was still far from the grasp. The
    expert paces its turn by the measured yaw, even where the arm travels far and turns
    slowly; an open-loop plan turns at the rate the wrist follows."""
    env = TwinEnv("pick_place")
    far = TaskConfig(object=(0.45, -0.3, math.radians(85)), target=(0.45, -0.1, 0.0))
    expert = env.task.expert(far, np.random.default_rng(0))
    assert _largest_turn_lead(env, far, lambda obs, t: expert.act(obs), 30) < 4.0
    near = TaskConfig(object=(0.45, 0.0, math.radians(85)), target=(0.45, -0.2, 0.0))
    plan = plan_demo(env.task, env.cell, near, np.random.default_rng(0))
    assert plan is not None
    assert _largest_turn_lead(env, near, lambda obs, t: plan.actions[t], 30) < 4.0
    far_plan = plan_demo(env.task, env.cell, far, np.random.default_rng(0))
    assert far_plan is not None and np.abs(far_plan.actions[:, 5]).max() <= TRACKED_ROTATION + 1e-6


def test_a_reaimed_expert_grasps_where_the_object_is_seen_to_be():
    """An expert whose grasp was chosen from a view 5 cm off is re-aimed on its way
    down (the seeing operator's aim following its sharper estimates): it grasps the
    banana where it is; once the fingers close it is no longer re-aimed."""
    env = TwinEnv("pick_place")
    config = env.task.sample_config(np.random.default_rng(5), "ID")
    observation, _ = env.reset(options={"config": config})
    expert = env.task.expert(config, np.random.default_rng(0))
    names = env.task.scene.object_names
    column = slice(7 * names.index("banana"), 7 * names.index("banana") + 3)
    yaw = config.object[2]
    off = 0.05 * np.array([-np.sin(yaw), np.cos(yaw), 0.0])  # across the banana

    def seen(obs):  # the view the grasp is planned on: the banana 5 cm across from where it is
        shown = dict(obs)
        environment = np.array(obs["observation.environment_state"], copy=True)
        environment[column] += off
        shown["observation.environment_state"] = environment
        return shown

    assert not expert.reaim(np.ones(3))  # no grasp chosen yet
    action = expert.act(seen(observation))
    aimed = expert.memory["grasp"][0].copy()
    assert expert.reaim(-off)  # approaching: seen better, the aim follows
    np.testing.assert_allclose(expert.memory["grasp"][0], aimed - off)
    for _ in range(env.task.max_steps):
        observation, _, terminated, _, info = env.step(action)
        if terminated:
            break
        if expert.phase == "close":
            before = expert.memory["grasp"][0].copy()
            assert not expert.reaim(np.ones(3))
            np.testing.assert_array_equal(expert.memory["grasp"][0], before)
        action = expert.act(observation)
    assert info["success"]
