"""The locating head's error replayed over logged episodes (``twinrl locate``)."""

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from tests.conftest import record_demos
from tests.test_cli import twinrl
from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_learn.cli import app
from twinrl_learn.cli.evaluation import labelled_sources
from twinrl_learn.locating import BANDS_CM, episode_errors
from twinrl_learn.policy import Policy
from twinrl_learn.settings import SFTConfig
from twinrl_learn.sft import train_sft


@pytest.fixture(scope="module")
def demos_and_policy(tmp_path_factory):
    """A demo with both cameras and object poses, and an image policy with a locating
    head briefly trained on it."""
    folder = tmp_path_factory.mktemp("locating")
    dataset = record_demos(folder, seed=3)
    out = folder / "vla"
    train_sft(
        SFTConfig(datasets=[str(dataset)], out=str(out), policy="vla", steps=2, batch_size=4,
                  image_size=64)
    )  # fmt: skip
    return folder, out


def test_the_error_is_the_planar_distance_between_located_and_true_offsets(demos_and_policy):
    folder, checkpoint = demos_and_policy
    policy = Policy.from_pretrained(checkpoint)
    episode = read_episode(Session(folder / "session").episode_paths()[0])
    state = episode.data["observation.state"]
    env = episode.data["observation.environment_state"]
    true = policy.locating_targets(state, env)["objects"]
    # Every object located 3 cm off in x and 4 cm in y (offsets are in decimetres), and
    # 1 m off in height, which the planar error leaves out.
    shift = torch.tensor([0.3, 0.4, 10.0]).repeat(len(policy.config.object_indices))
    policy.locate = lambda batch: true[: len(batch["state"])] + shift
    error, distance = episode_errors(policy, episode)
    assert error.shape == distance.shape == (len(episode), 2)
    assert np.allclose(error, 5.0, atol=1e-4)
    tcp = state[:, 12:15]
    assert np.allclose(distance[:, 0], np.linalg.norm(env[:, 0:3] - tcp, axis=1) * 100, atol=1e-3)


def test_locate_command_reports_each_source_and_refuses_bad_input(demos_and_policy, tmp_path):
    folder, checkpoint = demos_and_policy
    out = tmp_path / "loc"
    result = CliRunner().invoke(
        app,
        ["locate", str(checkpoint), f"demos={folder / 'dataset'}", str(folder / "session"),
         "--out", str(out)],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    report = json.loads((out / "locating.json").read_text())
    assert set(report["sources"]) == {"demos", folder.name}  # a session takes its parent's name
    for regions in report["sources"].values():
        objects = regions["ID"]
        assert set(objects) == {"banana", "plate"}
        banana = objects["banana"]
        assert banana["episodes"] == 1 and len(banana["frames"]) == len(BANDS_CM) - 1
        assert sum(banana["frames"]) > 0 and banana["first_frame_cm"] > 0
    # The same frames read from the dataset and from the session's MCAP files.
    demos, session = (report["sources"][k]["ID"]["banana"] for k in ("demos", folder.name))
    assert demos["frames"] == session["frames"]
    assert (out / "locating.png").stat().st_size > 0
    assert "median planar locating error" in result.output

    before = (out / "locating.json").read_bytes()
    again = twinrl("locate", str(checkpoint), str(folder / "session"), "--out", str(out))
    assert again.returncode != 0 and "exists and is not empty" in again.stderr
    assert (out / "locating.json").read_bytes() == before
    for nowhere in (str(tmp_path / "nope"), f"label={tmp_path / 'nope'}"):
        missing = twinrl("locate", str(checkpoint), nowhere, "--out", str(tmp_path / "x"))
        assert missing.returncode != 0 and "nope does not exist" in missing.stderr
    plain = tmp_path / "plain"
    train_sft(
        SFTConfig(datasets=[str(folder / "dataset")], out=str(plain), policy="vla", steps=1,
                  batch_size=4, image_size=64, locate_weight=0.0)
    )  # fmt: skip
    headless = twinrl("locate", str(plain), str(folder / "session"), "--out", str(tmp_path / "y"))
    assert headless.returncode != 0 and "neither locates the objects" in headless.stderr
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_sources_are_paths_or_labelled_paths(tmp_path):
    (tmp_path / "lr=1" / "session").mkdir(parents=True)
    (tmp_path / "data").mkdir()
    sources = labelled_sources(
        [str(tmp_path / "lr=1" / "session"), f"twin demos={tmp_path / 'data'}", f"x={tmp_path}"]
    )
    assert sources == {
        "lr=1": tmp_path / "lr=1" / "session",  # an existing path, '=' and all
        "twin demos": tmp_path / "data",
        "x": tmp_path,
    }
    with pytest.raises(ValueError, match="two sources are labelled 'data'"):
        labelled_sources([str(tmp_path / "data"), f"data={tmp_path}"])
