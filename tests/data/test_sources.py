"""One opener for every episode source: .mcap, session, LeRobot dataset, catalog."""

import numpy as np
import pytest

from tests.data.conftest import make_meta, make_step
from twinrl_data.catalog import build_index
from twinrl_data.errors import DataError
from twinrl_data.lerobot_io import export_dataset
from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_data.sources import discover_episodes, open_episode, open_episodes


@pytest.fixture
def sources(tmp_path):
    session = Session.create(tmp_path / "session")
    rng = np.random.default_rng(0)
    for i, success in enumerate((True, False, True)):
        with session.record(make_meta(config={"object": [i, 0, 0], "target": [0, 0, 0]})) as log:
            for t in range(4):
                log.append(make_step(t, 4, rng, cameras=(), **{"next.success": success}))
    export_dataset((read_episode(p) for p in session.episode_paths()), tmp_path / "dataset")
    build_index([tmp_path / "session"], tmp_path / "catalog.parquet")
    return tmp_path


def objects(episodes):
    return [e.meta.config["object"][0] for e in episodes]


def test_every_kind_of_source_opens_the_same_way(sources):
    for name in ("session", "dataset", "catalog.parquet"):
        episodes, count = open_episodes(sources / name)
        assert count == 3 and objects(episodes) == [0, 1, 2], name
    first = Session(sources / "session").episode_paths()[0]
    episodes, count = open_episodes(first)
    assert count == 1 and objects(episodes) == [0]
    selected, count = open_episodes(sources / "catalog.parquet", where="success")
    assert count == 2 and objects(selected) == [0, 2]


def test_one_episode_by_number_and_everything_under_a_folder(sources):
    assert open_episode(f"{sources / 'session'}#2").meta.config["object"][0] == 2
    assert open_episode(sources / "dataset", default_index=1).meta.config["object"][0] == 1
    assert len(discover_episodes([sources])) == 6  # the session and the dataset beside it


def test_wrong_sources_say_what_is_accepted(sources, tmp_path):
    with pytest.raises(DataError, match="is not a session folder, an .mcap episode"):
        open_episodes(tmp_path / "nothing")
    with pytest.raises(DataError, match="filter selects rows of a catalog"):
        open_episodes(sources / "session", where="success")
    with pytest.raises(DataError, match="has 3 episodes; episode 7 is out of range"):
        open_episode(f"{sources / 'session'}#7")
    with pytest.raises(DataError, match="must be an episode number"):
        open_episode(f"{sources / 'session'}#last")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="holds no session"):
        discover_episodes([tmp_path / "empty"])
