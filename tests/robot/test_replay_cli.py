"""``twinrl replay``: a logged episode re-sent through the safety layer, after the
start pose is shown and confirmed, recorded as a new episode and overlaid in Rerun."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.test_cli import twinrl
from twinrl_data.session import Session
from twinrl_robot.scripted import run_scripted_expert


@pytest.fixture(scope="module")
def logged(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("logged") / "session"
    run_scripted_expert(
        "pick_place", world="plant", episodes=1, regions=("ID",), session=Session.create(folder)
    )
    return folder


def test_a_replay_in_the_plant_retraces_the_log_and_is_recorded(logged, tmp_path) -> None:
    out, overlay = tmp_path / "replays", tmp_path / "overlay.rrd"
    result = twinrl(
        "replay",
        f"{logged}#0",
        "--robot",
        "plant",
        "--out",
        str(out),
        "--yes",
        "--rerun",
        str(overlay),
    )
    assert result.returncode == 0, result.stderr
    assert "steps replayed" in result.stdout and overlay.stat().st_size > 0
    (path,) = out.rglob("*.mcap")
    from twinrl_data.mcap_log import read_episode

    replay = read_episode(path, images=False)
    assert replay.meta.source == "replay" and replay.meta.policy.startswith("replay:")


def test_an_unconfirmed_replay_moves_nothing(logged, tmp_path) -> None:
    out = tmp_path / "replays"
    result = twinrl("replay", f"{logged}#0", "--robot", "plant", "--out", str(out), stdin="n\n")
    assert result.returncode == 2 and "not confirmed" in result.stderr
    assert not list(out.rglob("*.mcap"))


@pytest.mark.parametrize(
    ("options", "said"),
    [
        (["--robot", "ur"], "--robot ur needs the arm's --cell file"),
        (["--robot", "plant", "--cell", "cell.yaml"], "describe a UR arm; add --robot ur"),
        (["--robot", "arm"], "--robot must be one of ur, plant, twin"),
    ],
)
def test_a_replay_without_its_arm_is_refused_in_one_line(logged, tmp_path, options, said) -> None:
    out = tmp_path / "replays"
    result = twinrl("replay", f"{logged}#0", *options, "--out", str(out), "--yes")
    assert result.returncode == 2 and said in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and not out.exists()
