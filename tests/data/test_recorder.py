"""The Recorder: start_episode / add_frame / save_episode into a session or a folder."""

import numpy as np
import pytest

from twinrl_data.errors import DataError
from twinrl_data.mcap_log import read_episode
from twinrl_data.recorder import EpisodeFolder, Recorder
from twinrl_data.schema import EpisodeMeta, step_record
from twinrl_data.session import Session


def frame(t, success=False):
    obs = {"observation.state": np.full(4, t, np.float32)}
    return step_record(obs, np.zeros(7, np.float32), np.zeros(6, np.float32), 0.0, success, success)


def test_episodes_are_recorded_one_at_a_time_into_a_session(tmp_path):
    session = Session.create(tmp_path / "s")
    recorder = Recorder(session)
    assert not recorder.recording and recorder.frames == 0
    recorder.start_episode(EpisodeMeta(task="t", source="teleop", world="plant"))
    with pytest.raises(DataError, match="still open; save_episode"):
        recorder.start_episode(EpisodeMeta(task="t", source="teleop", world="plant"))
    for t in range(3):
        recorder.add_frame(frame(t, success=t == 2))
    assert recorder.recording and recorder.frames == 3
    path = recorder.save_episode()
    assert recorder.saved.success and not recorder.recording
    episode = read_episode(path)
    np.testing.assert_array_equal(episode.data["observation.state"][:, 0], [0, 1, 2])
    assert Session(tmp_path / "s").entries[0]["status"] == "complete"
    with pytest.raises(DataError, match="no episode is open"):
        recorder.add_frame(frame(0))


def test_a_malformed_frame_is_refused_and_the_episode_goes_on(tmp_path):
    recorder = Recorder(EpisodeFolder(tmp_path / "loose", prefix="ID_00001_"))
    recorder.start_episode(EpisodeMeta(task="t", source="twin_demo", world="twin"))
    recorder.add_frame(frame(0))
    with pytest.raises(DataError, match="must be a vector"):
        recorder.add_frame({**frame(1), "action": np.zeros((2, 7))})
    recorder.add_frame(frame(1))
    path = recorder.save_episode(success=False)
    assert path.parent == tmp_path / "loose" and path.name.startswith("ID_00001_")
    assert len(read_episode(path)) == 2
