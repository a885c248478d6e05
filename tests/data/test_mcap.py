"""MCAP episodes: round trip, schemas, Rerun, crash safety, recovery, fuzzing."""

import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from tests.data.conftest import make_meta, write_episode
from twinrl_data.errors import DataError, McapError
from twinrl_data.mcap_log import EpisodeWriter, read_episode, read_meta
from twinrl_data.salvage import recover


def test_round_trip_keeps_every_field_in_order(episode_file):
    path, steps = episode_file
    episode = read_episode(path)
    assert len(episode) == len(steps)
    for key in ("observation.state", "action", "action.policy", "command.joint_target"):
        np.testing.assert_allclose(episode.data[key], np.stack([s[key] for s in steps]), rtol=1e-6)
    np.testing.assert_array_equal(episode.data["intervention"], [s["intervention"] for s in steps])
    np.testing.assert_allclose(
        episode.data["next.reward"], [s["next.reward"] for s in steps], rtol=1e-6
    )
    assert episode.cameras == ["front", "wrist"]
    assert (
        np.abs(
            episode.images["front"].astype(int)
            - np.stack([s["observation.images.front"] for s in steps])
        ).mean()
        < 3
    )
    meta = episode.meta
    assert meta.success is True and meta.num_interventions == 3
    assert meta.config == {"object": [0.4, -0.2, 0.1], "target": [0.5, -0.1, 0.0]}
    assert read_meta(path) == meta


def test_png_is_lossless(tmp_path):
    path = tmp_path / "png.mcap"
    steps = write_episode(path, image_format="png")
    frames = read_episode(path).images["wrist"]
    np.testing.assert_array_equal(frames, np.stack([s["observation.images.wrist"] for s in steps]))


def test_channels_use_foxglove_and_project_schemas(episode_file):
    path, _ = episode_file
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    schemas = {summary.schemas[c.schema_id].name for c in summary.channels.values()}
    topics = {c.topic for c in summary.channels.values()}
    assert {
        "foxglove.CompressedImage",
        "foxglove.FrameTransforms",
        "twinrl.FloatVector",
        "twinrl.Transition",
    } <= schemas
    assert {"/camera/front", "/camera/wrist", "/tf", "/observation/state", "/transition"} <= topics


def test_rerun_cli_converts_a_recorded_episode(episode_file, tmp_path):
    path, _ = episode_file
    rerun = shutil.which("rerun", path=os.path.dirname(sys.executable))
    out = tmp_path / "episode.rrd"
    converted = subprocess.run(
        [rerun, "mcap", "convert", str(path), "-o", str(out)], capture_output=True, text=True
    )
    assert converted.returncode == 0, converted.stderr
    printed = subprocess.run([rerun, "rrd", "print", str(out)], capture_output=True, text=True)
    assert printed.returncode == 0, printed.stderr
    lines = printed.stdout.splitlines()
    assert any("/camera/front" in line and "EncodedImage:blob" in line for line in lines)
    assert any("/tf" in line and "Transform3D:translation" in line for line in lines)
    assert any("/observation/state" in line and "twinrl.FloatVector" in line for line in lines)


def test_bad_steps_are_reported_all_at_once(tmp_path):
    with EpisodeWriter(tmp_path / "bad.mcap", make_meta()) as log, pytest.raises(DataError) as err:
        log.append({"observation.state": np.zeros((2, 2)), "bogus": 1})
    message = str(err.value)
    assert (
        "missing ['action']" in message
        and "unknown field(s) ['bogus']" in message
        and "vector" in message
    )


def test_nothing_is_overwritten(episode_file):
    path, _ = episode_file
    before = path.read_bytes()
    with pytest.raises(McapError, match="already exists"):
        EpisodeWriter(path, make_meta())
    assert path.read_bytes() == before


def test_missing_foreign_and_truncated_files(tmp_path, episode_file):
    with pytest.raises(McapError, match="does not exist"):
        read_episode(tmp_path / "nope.mcap")
    text = tmp_path / "text.mcap"
    text.write_text("hello")
    with pytest.raises(McapError, match="not an MCAP file"):
        read_episode(text)
    path, _ = episode_file
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
    with pytest.raises(McapError, match="twinrl data recover"):
        read_episode(cut)


RECORDER = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    from tests.data.conftest import make_meta, make_step
    from twinrl_data.mcap_log import EpisodeWriter
    rng = np.random.default_rng(0)
    with EpisodeWriter(sys.argv[1], make_meta(), flush_seconds=1.0) as log:
        for t in range(1000):
            log.append(make_step(t, 1000, rng))
            print(t, flush=True)
            time.sleep(0.1)  # real time at 10 Hz
    """
)


def test_a_killed_recorder_loses_at_most_one_second(tmp_path):
    path = tmp_path / "killed.mcap"
    root = os.path.dirname(os.path.dirname(os.path.dirname(__file__)))
    proc = subprocess.Popen(
        [sys.executable, "-c", RECORDER, str(path)], stdout=subprocess.PIPE, text=True, cwd=root
    )
    written = -1
    deadline = time.time() + 60
    while written < 34 and time.time() < deadline:
        written = int(proc.stdout.readline())
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    with pytest.raises(McapError):
        read_episode(path)
    result = recover(path)
    assert not result.complete
    episode = read_episode(result.output)
    assert written + 1 - len(episode) <= 10  # at most one second of 10 Hz steps lost
    assert episode.meta.task == "pick_place" and episode.meta.success is None
    with pytest.raises(McapError, match="already exists"):
        recover(path)


def test_recovering_a_complete_file_keeps_everything(episode_file, tmp_path):
    path, steps = episode_file
    result = recover(path, tmp_path / "copy.mcap")
    assert result.complete and result.metadata == 3
    assert len(read_episode(result.output)) == len(steps)


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.binary(max_size=4096))
def test_random_bytes_raise_the_projects_error(tmp_path, data):
    path = tmp_path / "fuzz.mcap"
    path.write_bytes(data)
    with pytest.raises(McapError):
        read_episode(path)


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(cut=st.integers(min_value=0), flip=st.integers(min_value=0), value=st.integers(0, 255))
def test_truncated_or_corrupted_logs_raise_the_projects_error(tmp_path, cut, flip, value):
    source = tmp_path / "source.mcap"
    if not source.exists():
        write_episode(source, length=4)
    raw = bytearray(source.read_bytes())
    raw = raw[: cut % len(raw)]
    if raw:
        raw[flip % len(raw)] = value
    path = tmp_path / "damaged.mcap"
    path.write_bytes(bytes(raw))
    try:
        episode = read_episode(path)
    except McapError:
        return
    assert len(episode) <= 4  # a flipped byte inside image data can still decode
