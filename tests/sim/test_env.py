"""Gymnasium envs: API conformance, reset from a logged config, replay determinism."""

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from tests.conftest import TASK_NAMES, expert_commands
from twinrl_sim import GYM_IDS
from twinrl_sim.env import TwinEnv


@pytest.mark.parametrize("name", TASK_NAMES)
def test_env_passes_the_gymnasium_checker(name):
    env = TwinEnv(name, images=(name == "pick_place"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # unbounded Box warnings are expected for poses
        check_env(env, skip_render_check=True)
    obs, _ = env.reset(seed=0)
    assert obs["observation.state"].shape == (20,)
    assert obs["observation.environment_state"].shape == (14,)
    assert np.all(np.isfinite(obs["observation.state"]))


def test_images_follow_the_contract():
    env = TwinEnv("erase_whiteboard", images=True)
    obs, _ = env.reset(seed=1)
    for cam in ("front", "wrist"):
        image = obs[f"observation.images.{cam}"]
        assert image.shape == (128, 128, 3) and image.dtype == np.uint8
        assert image.std() > 5  # not a blank frame


def test_reset_from_a_logged_config_regenerates_the_exact_state():
    env = TwinEnv("insert_hexagon")
    _, info = env.reset(seed=7, options={"region": "OOD"})
    first = env.cell.get_state()
    other = TwinEnv("insert_hexagon")
    other.reset(seed=99)
    other.step(other.action_space.sample())
    other.reset(options={"config": info["config"]})
    np.testing.assert_array_equal(other.cell.get_state(), first)


def test_same_seed_same_episode():
    runs = []
    for _ in range(2):
        env = TwinEnv("pick_place")
        env.reset(seed=5)
        env.action_space.seed(5)
        for _ in range(10):
            obs, *_ = env.step(env.action_space.sample())
        runs.append(obs["observation.state"])
    np.testing.assert_array_equal(*runs)


def test_replay_is_deterministic_and_reproduces_the_episode(rng):
    env = TwinEnv("pick_place")
    config = env.task.sample_config(rng, "ID")
    targets, gripper = expert_commands(env, config, steps=30)
    lived = env.cell.state_vector()
    first = env.replay(config, targets, gripper)
    second = TwinEnv("pick_place").replay(config.to_dict(), targets, gripper)
    np.testing.assert_array_equal(first.state, second.state)
    # The targets come back as logged (float32): joint angles and the TCP pose replay
    # to 1e-6, joint velocities, which differentiate them, to 1e-5 rad/s.
    velocities = slice(6, 12)
    np.testing.assert_allclose(first.state[-1, velocities], lived[velocities], atol=1e-5)
    np.testing.assert_allclose(
        np.delete(first.state[-1], velocities), np.delete(lived, velocities), atol=1e-6
    )
    assert first.state.shape == (31, 20)


def test_bad_reset_and_replay_input_is_rejected():
    env = TwinEnv("pick_place")
    with pytest.raises(ValueError, match="unknown reset option"):
        env.reset(options={"confg": {}})
    with pytest.raises(ValueError, match=r"shape \(T, 6\)"):
        env.replay({"object": [0.4, -0.2, 0], "target": [0.5, -0.1, 0]}, np.zeros((5, 5)))
    with pytest.raises(RuntimeError, match="reset"):
        TwinEnv("pick_place").step(np.zeros(7))


def test_registered_ids_make_envs_and_vector_envs():
    env = gym.make(GYM_IDS["insert_triple_column"])
    obs, _ = env.reset(seed=0)
    assert "observation.state" in obs
    vec = gym.make_vec(GYM_IDS["pick_place"], num_envs=2, vectorization_mode="sync")
    obs, _ = vec.reset(seed=0)
    assert obs["observation.state"].shape == (2, 20)
