"""Episodes for data-layer tests, made without any simulator (the data layer stands alone)."""

import numpy as np
import pytest

from twinrl_data.schema import EpisodeMeta

STATE_NAMES = (
    [f"q.j{i}" for i in range(6)]
    + [f"qd.j{i}" for i in range(6)]
    + [
        "tcp.x",
        "tcp.y",
        "tcp.z",
        "tcp.qw",
        "tcp.qx",
        "tcp.qy",
        "tcp.qz",
        "gripper.opening",
    ]
)
ENV_NAMES = [f"cube.{s}" for s in ("x", "y", "z", "qw", "qx", "qy", "qz")]


def make_meta(**changes) -> EpisodeMeta:
    fields = dict(
        task="pick_place",
        instruction="put the banana on the plate",
        source="twin_demo",
        world="twin",
        region="ID",
        config={"object": [0.4, -0.2, 0.1], "target": [0.5, -0.1, 0.0]},
        twin="abc123",
        names={"observation.state": STATE_NAMES, "observation.environment_state": ENV_NAMES},
    )
    fields.update(changes)
    return EpisodeMeta(**fields)


def make_step(
    t: int, length: int, rng: np.random.Generator, cameras=("front", "wrist"), **extra
) -> dict:
    state = rng.normal(size=20).astype(np.float32)
    state[15:19] = [1, 0, 0, 0]
    step = {
        "observation.state": state,
        "observation.environment_state": np.array([0.4, -0.2, 0.02, 1, 0, 0, 0], np.float32),
        "action": rng.uniform(-0.01, 0.01, 7).astype(np.float32),
        "action.policy": rng.uniform(-0.01, 0.01, 7).astype(np.float32),
        "command.joint_target": rng.normal(size=6).astype(np.float32),
        "intervention": 5 <= t < 8,
        "next.reward": 10.0 if t == length - 1 else -0.05,
        "next.done": t == length - 1,
        "next.success": t == length - 1,
    }
    for camera in cameras:
        image = np.zeros((128, 128, 3), np.uint8)
        image[:, : 8 * (t % 16)] = 200  # a moving edge, easy to compress and to check
        step[f"observation.images.{camera}"] = image
    step.update(extra)
    return step


def write_episode(path, length=12, seed=0, meta=None, **writer_options):
    from twinrl_data.mcap_log import EpisodeWriter

    rng = np.random.default_rng(seed)
    steps = [make_step(t, length, rng) for t in range(length)]
    with EpisodeWriter(path, meta or make_meta(), **writer_options) as log:
        for step in steps:
            log.append(step)
    return steps


@pytest.fixture
def episode_file(tmp_path):
    path = tmp_path / "episode.mcap"
    steps = write_episode(path)
    return path, steps
