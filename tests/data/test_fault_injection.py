"""Fault injection: recorders and indexers killed with SIGKILL at seeded random points.

After every kill, each finished episode is still listed and reads exactly; nothing
unfinished is listed as finished; ``data repair`` recovers the unfinished ones. A quick
subset runs by default; the full set is marked slow.
"""

import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from twinrl_data.catalog import build_index, query
from twinrl_data.mcap_log import read_episode, read_summary
from twinrl_data.repair import repair_session
from twinrl_data.session import Session

ROOT = Path(__file__).resolve().parents[2]

RECORDER = """
    import sys
    import numpy as np
    from tests.data.conftest import make_meta, make_step
    from twinrl_data.recorder import Recorder
    from twinrl_data.session import Session
    recorder = Recorder(Session.create(sys.argv[1], exist_ok=True), flush_seconds=0.3)
    rng = np.random.default_rng(int(sys.argv[2]))
    while True:
        recorder.start_episode(make_meta())
        for t in range(15):
            recorder.add_frame(make_step(t, 15, rng, cameras=("front",)))
            print("frame", flush=True)
        recorder.save_episode()
"""


def _kill_after(code: str, frames: int, *args: str) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(code), *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    for _ in range(frames):
        if not proc.stdout.readline():
            break
    proc.send_signal(signal.SIGKILL)
    proc.wait()


def _check_session(path: Path) -> int:
    """Every finished episode reads exactly; returns how many there are."""
    session = Session(path)
    numbers = [Path(e["file"]).name[:6] for e in session.entries]
    assert len(numbers) == len(set(numbers)), "two episodes share a number"
    readable = session.readable_paths()
    assert len(readable) >= sum(e["status"] == "complete" for e in session.entries)
    for file in readable:
        assert len(read_episode(file)) == read_summary(file).length == 15
    return len(readable)


def _recording_kills(tmp_path: Path, kills: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    finished = 0
    for kill in range(kills):
        _kill_after(RECORDER, int(rng.integers(1, 60)), str(tmp_path / "s"), str(kill))
        now = _check_session(tmp_path / "s")
        assert now >= finished, "a finished episode was lost"
        finished = now
    report = repair_session(tmp_path / "s")
    assert report.missing == [] and report.unreadable == []
    repaired = Session(tmp_path / "s")
    assert not repaired.problems
    # A kill between an episode's file being finished and its manifest entry being
    # updated leaves a finished file listed as recording: repair lists it as finished.
    assert len(repaired.readable_paths()) >= finished + len(report.recovered)
    files = list((tmp_path / "s" / "episodes").glob("*.mcap"))
    assert len(repaired.readable_paths()) == len(files)  # every file left is listed
    for file in repaired.readable_paths():
        read_episode(file, images=False)


def test_recorders_killed_at_random_points_lose_no_finished_episode(tmp_path):
    _recording_kills(tmp_path, kills=3, seed=0)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(2))
def test_recorders_killed_at_random_points_many_seeds(tmp_path, seed):
    _recording_kills(tmp_path, kills=10, seed=seed)


INDEXER = """
    import sys
    from twinrl_data.catalog import build_index
    print("start", flush=True)
    while True:
        build_index([sys.argv[1]], sys.argv[2])
        print("frame", flush=True)
"""


def test_an_indexer_killed_at_random_points_leaves_the_old_catalog_or_the_new(tmp_path):
    from tests.data.test_data_safety import _record

    _record(Session.create(tmp_path / "s"), 3)
    catalog = tmp_path / "catalog.parquet"
    build_index([tmp_path / "s"], catalog)
    rng = np.random.default_rng(3)
    for _ in range(3):
        _kill_after(INDEXER, int(rng.integers(1, 4)), str(tmp_path / "s"), str(catalog))
        assert query(catalog).num_rows == 3
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
