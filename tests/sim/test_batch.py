"""Batched simulation agrees with stepping envs one at a time."""

import gymnasium as gym
import numpy as np

from tests.conftest import expert_commands
from twinrl_sim import GYM_IDS
from twinrl_sim.batch import BatchEnv, BatchRollout
from twinrl_sim.env import TwinEnv


def test_batch_env_is_bit_identical_to_single_envs(rng):
    env = TwinEnv("erase_whiteboard")
    configs = [env.task.sample_config(rng, r) for r in ("ID", "OOD", "ID")]
    finals = []
    for i, config in enumerate(configs):
        expert = env.task.expert(config, np.random.default_rng(i))
        obs, _ = env.reset(options={"config": config})
        for _ in range(25):
            obs, *_ = env.step(expert.act(obs))
        finals.append(obs["observation.state"])
    batch = BatchEnv("erase_whiteboard", len(configs))
    experts = [env.task.expert(c, np.random.default_rng(i)) for i, c in enumerate(configs)]
    obs = batch.reset(configs)
    for _ in range(25):
        actions = np.stack(
            [e.act({k: v[i] for k, v in obs.items()}) for i, e in enumerate(experts)]
        )
        obs, rewards, terminated, truncated, info = batch.step(actions)
    np.testing.assert_array_equal(obs["observation.state"], np.stack(finals))
    assert rewards.shape == terminated.shape == truncated.shape == (3,)
    assert info["command.joint_target"].shape == (3, 6)


def test_batch_rollout_matches_replay(rng):
    env = TwinEnv("pick_place")
    configs = [env.task.sample_config(rng, "OOD") for _ in range(3)]
    commands = [expert_commands(env, c, seed=i, steps=20) for i, c in enumerate(configs)]
    targets = np.stack([t for t, _ in commands])
    gripper = np.stack([g for _, g in commands])
    result = BatchRollout("pick_place").run(configs, targets, gripper)
    assert result.states.shape[:2] == (3, 21)
    for i, config in enumerate(configs):
        alone = env.replay(config, targets[i], gripper[i])
        np.testing.assert_allclose(result.arm_q()[i], alone.state[:, :6], atol=1e-6)


def test_async_vector_env_runs_in_worker_processes():
    """Spawned workers (fork is unsafe once simulation threads exist) import twinrl_sim."""
    vec = gym.make_vec(
        f"twinrl_sim:{GYM_IDS['pick_place']}",
        num_envs=2,
        vectorization_mode="async",
        vector_kwargs={"context": "spawn"},
    )
    try:
        obs, _ = vec.reset(seed=3)
        obs, rewards, *_ = vec.step(np.zeros((2, 7), np.float32))
        assert obs["observation.state"].shape == (2, 20) and rewards.shape == (2,)
    finally:
        vec.close()
