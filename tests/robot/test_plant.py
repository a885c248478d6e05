"""The plant: hidden effects, noise and its own clock behind the robot interface."""

import numpy as np
import pytest

from twinrl_robot.backends import open_robot
from twinrl_robot.plant import DEFAULT_EFFECTS_FILE
from twinrl_robot.robot import Robot
from twinrl_robot.scripted import run_scripted_expert
from twinrl_robot.wrappers import NoiseLevels
from twinrl_sim.env import TwinEnv
from twinrl_sim.tasks import TaskConfig

CONFIG = TaskConfig(object=(0.45, -0.2, 0.3), target=(0.5, -0.08, 0.0))
QUIET = NoiseLevels(
    joint_noise=0,
    velocity_noise=0,
    tcp_noise=0,
    object_noise=0,
)
SWING = np.array([0.02, 0.03, -0.01, 0.0, 0.0, 0.2, 0.0], np.float32)


def Plant(task, *, effects=None, settings=None, seed=None, images=()):
    """The plant as every caller opens it."""
    return open_robot("plant", task, effects=effects, noise=settings, seed=seed, cameras=images)


def drive(world, steps=15):
    for _ in range(steps):
        world.act(SWING)
    return world.observe()["observation.state"]


def test_plant_is_a_robot_and_counts_real_time():
    plant = Plant("pick_place", seed=0)
    assert isinstance(plant, Robot)
    plant.reset(CONFIG)
    sent = [plant.act(SWING) for _ in range(12)]
    cell = plant.unwrapped
    assert cell.elapsed_steps == 12 and cell.elapsed_seconds == pytest.approx(1.2)
    assert sent[-1].joint_target is not None and sent[-1].joint_target.shape == (6,)


def test_without_effects_or_noise_the_plant_behaves_like_the_twin():
    plant = Plant("pick_place", effects={}, settings=QUIET)
    plant.reset(CONFIG)
    env = TwinEnv("pick_place")
    env.reset(options={"config": CONFIG})
    for _ in range(15):
        twin_obs, *_ = env.step(SWING)
    np.testing.assert_allclose(drive(plant), twin_obs["observation.state"], atol=1e-9)


def test_hidden_effects_make_the_plant_differ_from_the_twin():
    quiet_twin_like = Plant("pick_place", effects={}, settings=QUIET)
    hidden = Plant("pick_place", effects=DEFAULT_EFFECTS_FILE, settings=QUIET)
    quiet_twin_like.reset(CONFIG)
    hidden.reset(CONFIG)
    assert np.abs(drive(hidden)[:6] - drive(quiet_twin_like)[:6]).max() > 1e-3


def test_noise_is_seeded_and_the_twin_never_sees_plant_effects():
    readings = []
    for _ in range(2):
        plant = Plant("pick_place", seed=11)
        readings.append(plant.reset(CONFIG)["observation.state"])
    np.testing.assert_array_equal(*readings)
    assert "effects" not in TwinEnv("pick_place").task.scene.model_dump(exclude_defaults=True)


def test_plant_renders_its_own_look():
    plant = Plant("pick_place", images=("front",))
    twin = TwinEnv("pick_place", images=True)
    plant_image = plant.reset(CONFIG)["observation.images.front"]
    twin_image = twin.reset(options={"config": CONFIG})[0]["observation.images.front"]
    assert plant_image.shape == twin_image.shape
    assert np.abs(plant_image.astype(int) - twin_image.astype(int)).mean() > 1.0


def test_misuse_is_reported():
    with pytest.raises(RuntimeError, match="reset the plant"):
        Plant("pick_place").act(SWING)
    with pytest.raises(ValueError, match="unknown effect"):
        Plant("pick_place", effects={"gravity": {"g": 1}})
    with pytest.raises(ValueError, match="must be >= 0"):
        NoiseLevels(joint_noise=-1)


def test_scripted_expert_solves_the_plant():
    report = run_scripted_expert("insert_hexagon", world="plant", episodes=10, seed=2)
    assert all(rate >= 0.9 for rate in report.success_rate().values())
    with pytest.raises(ValueError, match="plant only"):
        run_scripted_expert("pick_place", world="twin", effects={})


def test_the_expert_corrects_operator_jitter():
    steady = run_scripted_expert("pick_place", world="plant", episodes=5, regions=("ID",), seed=3)
    shaky = run_scripted_expert(
        "pick_place", world="plant", episodes=5, regions=("ID",), seed=3, action_noise=0.002
    )
    assert [e.steps for e in shaky.episodes] != [e.steps for e in steady.episodes]
    assert shaky.success_rate()["ID"] >= 0.8
