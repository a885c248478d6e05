"""Tasks: configurations, regions, success, rewards and the scripted experts' success."""

import numpy as np
import pytest

from tests.conftest import TASK_NAMES
from twinrl_robot.scripted import run_scripted_expert
from twinrl_sim.tasks import TaskConfig, make_task, task_class


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
    from twinrl_sim.env import TwinEnv

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
