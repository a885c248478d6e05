"""LeRobot datasets: export via lerobot's API, plain lerobot loading, import, training."""

import numpy as np
import pytest

from tests.conftest import lerobot_train
from tests.data.conftest import make_meta, write_episode
from twinrl_data.errors import DataError
from twinrl_data.lerobot_io import export_dataset, iter_dataset_episodes, open_dataset, read_sidecar
from twinrl_data.mcap_log import read_episode
from twinrl_data.training import make_dataloader


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    folder = tmp_path_factory.mktemp("lerobot")
    episodes = []
    for i, (source, region) in enumerate((("twin_demo", "ID"), ("teleop", "OOD"))):
        path = folder / f"ep{i}.mcap"
        write_episode(path, length=10 + i, seed=i, meta=make_meta(source=source, region=region))
        episodes.append(read_episode(path))
    result = export_dataset(episodes, folder / "dataset", repo_id="tests/pick_place")
    return result, episodes


def test_export_loads_in_plain_lerobot(exported):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    result, episodes = exported
    assert (result.episodes, result.frames) == (2, 21)
    dataset = LeRobotDataset("tests/pick_place", root=result.root, video_backend="pyav")
    assert dataset.meta.total_episodes == 2 and len(dataset) == 21
    item = dataset[3]
    assert item["observation.images.front"].shape == (3, 128, 128)
    assert item["task"] == "put the banana on the plate"
    np.testing.assert_allclose(
        item["observation.state"].numpy(), episodes[0].data["observation.state"][3], rtol=1e-6
    )
    assert dataset.meta.features["observation.state"]["names"][0] == "q.j0"


def test_episode_metadata_survives_the_round_trip(exported):
    result, episodes = exported
    sidecar = read_sidecar(result.root)
    assert [sidecar[i]["source"] for i in (0, 1)] == ["twin_demo", "teleop"]
    back = list(iter_dataset_episodes(result.root))
    for original, restored in zip(episodes, back, strict=True):
        assert restored.meta == original.meta
        np.testing.assert_allclose(restored.data["action"], original.data["action"], rtol=1e-6)
        np.testing.assert_array_equal(restored.data["intervention"], original.data["intervention"])
        assert (
            np.abs(
                restored.images["wrist"].astype(int) - original.images["wrist"].astype(int)
            ).mean()
            < 8
        )


def test_foreign_datasets_report_missing_fields_instead_of_inventing_them(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {
        "observation.state": {"dtype": "float32", "shape": (4,), "names": ["a", "b", "c", "d"]},
        "action": {"dtype": "float32", "shape": (2,), "names": ["x", "y"]},
    }
    dataset = LeRobotDataset.create(
        "someone/foreign", fps=30, features=features, root=tmp_path / "foreign"
    )
    for t in range(5):
        dataset.add_frame(
            {
                "observation.state": np.full(4, t, np.float32),
                "action": np.zeros(2, np.float32),
                "task": "stack",
            }
        )
    dataset.save_episode()
    dataset.finalize()
    (episode,) = iter_dataset_episodes(tmp_path / "foreign", source="teleop", world="real")
    assert set(episode.data) == {"observation.state", "action"}
    assert episode.meta.task == "stack" and episode.meta.fps == 30 and episode.meta.world == "real"


def test_export_refuses_to_overwrite_and_mixed_episodes(exported, tmp_path):
    result, episodes = exported
    with pytest.raises(DataError, match="already exists"):
        export_dataset(episodes, result.root)
    other = tmp_path / "other.mcap"
    write_episode(other, length=3)
    odd = read_episode(other)
    odd.data["action"] = odd.data["action"][:, :5]
    with pytest.raises(DataError, match="does not match the first one"):
        export_dataset([episodes[0], odd], tmp_path / "mixed")
    with pytest.raises(DataError, match="not a LeRobotDataset"):
        open_dataset(tmp_path)


def test_training_batches_with_windows(exported):
    result, _ = exported
    loader = make_dataloader(
        [result.root, result.root],
        batch_size=4,
        delta_timestamps={"action": [0.0, 0.1, 0.2]},
        seed=3,
    )
    batch = next(iter(loader))
    assert batch["action"].shape == (4, 3, 7)
    assert batch["action_is_pad"].shape == (4, 3)
    assert batch["observation.images.front"].shape == (4, 3, 128, 128)
    again = next(
        iter(
            make_dataloader(
                [result.root, result.root],
                batch_size=4,
                delta_timestamps={"action": [0.0, 0.1, 0.2]},
                seed=3,
            )
        )
    )
    assert (batch["index"] == again["index"]).all()
    with pytest.raises(DataError, match="no dataset"):
        make_dataloader([])


@pytest.mark.slow
def test_lerobots_own_trainer_starts_on_a_twinrl_dataset(exported, tmp_path):
    """lerobot-train runs a few ACT steps offline on an exported dataset."""
    result, _ = exported
    run = lerobot_train(result.root, tmp_path / "train", "--save_checkpoint=false", "--log_freq=1")
    assert run.returncode == 0, run.stderr[-2000:]
    assert "End of training" in run.stdout + run.stderr


def test_datasets_outside_the_contract_are_refused(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {"observation.joints": {"dtype": "float32", "shape": (3,), "names": ["a", "b", "c"]}}
    dataset = LeRobotDataset.create("someone/odd", fps=10, features=features, root=tmp_path / "odd")
    dataset.add_frame({"observation.joints": np.zeros(3, np.float32), "task": "wave"})
    dataset.save_episode()
    dataset.finalize()
    with pytest.raises(
        DataError,
        match=r"does not follow the episode contract: it lacks \['observation.state', 'action'\]",
    ):
        list(iter_dataset_episodes(tmp_path / "odd"))
