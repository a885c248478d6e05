"""Closing as low as the demonstrations close: the height read from demonstrations, the
rule that holds a close until the tool is there, and the policy that acts with it."""

import numpy as np
import pytest

from tests.conftest import record_demos
from twinrl_data.errors import SettingError
from twinrl_learn.policy import Policy, PolicyConfig
from twinrl_learn.policy.close_height import (
    DESCENT_STEP,
    MAX_HELD_STEPS,
    CloseHeightRule,
    demonstrated_close_height,
)
from twinrl_learn.runners import load_runner
from twinrl_learn.settings import SFTConfig
from twinrl_learn.sft import train_sft
from twinrl_sim.tasks.expert import GRIPPER_CLOSED


def offsets_at(height: float, lateral: float = 0.01) -> np.ndarray:
    """Two objects: one ``lateral`` beside the tool and ``height`` below it, one far."""
    return np.array([[lateral, 0.0, -height], [0.3, 0.2, -0.05]])


def test_the_close_height_is_read_where_each_demonstrated_close_starts():
    # Two episodes of 5 frames: the first closes at frame 2 (4 mm above the object),
    # opens and closes again at 4 (8 mm); the second is closed from its first frame
    # (5 mm). Frames after a close's first, and the far object, do not count.
    action = np.zeros((10, 7))
    action[:, -1] = [0, 0, 1, 0, 1, 1, 1, 1, 1, 1]
    episode_end = np.array([5] * 5 + [10] * 5)
    heights = [0.05, 0.03, 0.004, 0.0, 0.008, 0.005, 0.001, 0.001, 0.001, 0.001]
    offsets = np.stack([offsets_at(h) for h in heights])
    assert demonstrated_close_height(action, episode_end, offsets) == pytest.approx(0.005)
    offsets[5] = offsets_at(0.005, lateral=0.2)  # nothing under the tool: not counted
    assert demonstrated_close_height(action, episode_end, offsets) == pytest.approx(0.006)
    offsets[2] = np.nan  # a frame with no poses: not counted
    assert demonstrated_close_height(action, episode_end, offsets) == pytest.approx(0.008)
    action[:, -1] = 0.0  # never closed
    assert demonstrated_close_height(action, episode_end, offsets) is None


def test_a_close_waits_until_the_tool_is_down_at_the_demonstrated_height():
    rule = CloseHeightRule(close_height=0.001)
    close = np.array([0.01, 0.0, -0.005, 0.0, 0.0, 0.1, 1.0])
    height = {"now": 0.015}
    calls = []

    def offsets() -> np.ndarray:
        calls.append(height["now"])
        return offsets_at(height["now"])

    # 14 mm too high: down by one descent step, the gripper open, nothing else moves.
    held = rule(close, offsets)
    assert held[2] == pytest.approx(-DESCENT_STEP) and held[-1] < GRIPPER_CLOSED
    assert not np.any(np.delete(held, 2))
    height["now"] = 0.005  # 4 mm too high: down by what is left
    assert rule(close, offsets)[2] == pytest.approx(-0.004)
    height["now"] = 0.0025  # within the tolerance: the close goes through as commanded
    assert rule(close, offsets) is close
    assert rule(close, offsets) is close and len(calls) == 3  # closing: no more looking
    open_ = close.copy()
    open_[-1] = 0.0
    assert rule(open_, offsets) is open_  # opened: the next close is checked again
    height["now"] = 0.02
    assert rule(close, offsets)[-1] == 0.0


def test_a_close_is_held_a_few_steps_at_most_and_never_without_an_object_under_the_tool():
    close = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    rule = CloseHeightRule(close_height=0.0)
    held = [rule(close, lambda: offsets_at(0.05))[-1] for _ in range(MAX_HELD_STEPS + 2)]
    assert held == [0.0] * MAX_HELD_STEPS + [1.0, 1.0]
    rule.reset()
    assert rule(close, lambda: offsets_at(0.05, lateral=0.1)) is close


def state_policy(close_height: float | None) -> Policy:
    """A state policy whose state holds the TCP at (0.3, 0, 0.2) and whose environment
    one object 12 mm below it; it predicts a close."""
    config = PolicyConfig(
        kind="state", state_dim=8, env_dim=7, tcp_index=0, object_indices=[0],
        grasp_hold=False, close_height=close_height,
    )  # fmt: skip
    policy = Policy(config)
    close = np.array([0.0, 0.0, -0.004, 0.0, 0.0, 0.0, 1.0], np.float32)
    policy.act_chunks = lambda *a, **k: close[None, None]
    return policy


def test_the_policy_holds_its_close_as_its_checkpoint_says():
    observation = {
        "observation.state": np.array([0.3, 0.0, 0.2, 1, 0, 0, 0, 0.08], np.float32),
        "observation.environment_state": np.array([0.31, 0.0, 0.188, 1, 0, 0, 0], np.float32),
    }
    policy = state_policy(close_height=0.002)
    np.testing.assert_allclose(policy.object_offsets(observation), [[0.01, 0.0, -0.012]], atol=1e-6)
    acted = policy.act(observation, "")
    assert acted[2] == pytest.approx(-DESCENT_STEP) and acted[-1] == 0.0
    policy.config.close_as_demonstrated = False
    policy.reset()
    assert policy.act(observation, "")[-1] == 1.0
    policy = state_policy(close_height=None)  # saved before the height existed
    assert policy.act(observation, "")[-1] == 1.0


def test_sft_reads_the_demonstrations_close_height_and_eval_can_turn_it_off(tmp_path):
    """The scripted expert closes at the banana's centre (within millimetres); the state
    policy's checkpoint keeps that height, and a runner can act without it."""
    dataset = record_demos(tmp_path / "demos", episodes=2, seed=3)
    out = tmp_path / "policy"
    train_sft(
        SFTConfig(datasets=[str(dataset)], out=str(out), policy="state", steps=3, batch_size=8)
    )
    saved = Policy.from_pretrained(out)
    assert saved.config.close_height is not None and abs(saved.config.close_height) < 0.006
    runner = load_runner(out, close_as_demonstrated=False)
    assert not runner.policy.config.close_as_demonstrated and runner.name.endswith(
        ":close-as-predicted"
    )
    with pytest.raises(SettingError, match="close_as_demonstrated"):
        load_runner("expert", close_as_demonstrated=True)
