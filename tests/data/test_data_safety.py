"""Data safety: concurrent writers, a damaged manifest, a full disk, kills, permissions,
damaged files never read as good."""

import errno
import json
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from tests.data.conftest import make_meta, make_step, write_episode
from tests.test_cli import twinrl
from twinrl_data import atomic, mcap_log
from twinrl_data.errors import DataError, DataWarning, McapError
from twinrl_data.locking import FolderLock
from twinrl_data.mcap_log import read_episode
from twinrl_data.recorder import Recorder
from twinrl_data.repair import repair_session, verify
from twinrl_data.session import MANIFEST, Session
from twinrl_data.sources import open_episodes

ROOT = Path(__file__).resolve().parents[2]


def _record(session: Session, episodes: int, length: int = 6, seed: int = 0) -> list[Path]:
    rng = np.random.default_rng(seed)
    recorder = Recorder(session)
    paths = []
    for _ in range(episodes):
        recorder.start_episode(make_meta())
        for t in range(length):
            recorder.add_frame(make_step(t, length, rng, cameras=()))
        paths.append(recorder.save_episode())
    return paths


def _python(code: str, *args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(code), *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


WRITER = """
    import sys
    from pathlib import Path
    from tests.data.test_data_safety import _record
    from twinrl_data.session import Session
    session = Session.create(Path(sys.argv[1]), exist_ok=True)
    _record(session, int(sys.argv[2]), seed=int(sys.argv[3]))
"""


@pytest.mark.parametrize("writers", [2, 3])
def test_concurrent_writers_each_keep_every_episode_under_its_own_number(tmp_path, writers):
    Session.create(tmp_path / "s")
    procs = [_python(WRITER, str(tmp_path / "s"), "6", str(i)) for i in range(writers)]
    for proc in procs:
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, err
    session = Session(tmp_path / "s")
    files = sorted((tmp_path / "s" / "episodes").glob("*.mcap"))
    assert len(session.entries) == len(files) == 6 * writers
    numbers = [p.name[:6] for p in files]
    assert len(set(numbers)) == len(numbers)
    assert not session.problems
    assert all(len(read_episode(p, images=False)) == 6 for p in session.readable_paths())


HOLDER = """
    import sys, time
    from twinrl_data.locking import FolderLock
    with FolderLock(sys.argv[1]):
        print("held", flush=True)
        time.sleep(60)
"""


def test_a_held_lock_is_refused_naming_its_holder_and_a_killed_holder_frees_it(tmp_path):
    holder = _python(HOLDER, str(tmp_path))
    assert holder.stdout.readline().strip() == "held"
    refused = pytest.raises(DataError, match=rf"locked by process {holder.pid} on .* since ")
    with refused, FolderLock(tmp_path, wait=0.3):
        pass
    holder.send_signal(signal.SIGKILL)
    holder.wait()
    start = time.monotonic()
    with FolderLock(tmp_path, wait=5):  # the stale lock file does not block
        pass
    assert time.monotonic() - start < 1.0


def test_a_damaged_manifest_is_read_from_the_files_and_repaired(tmp_path):
    session = Session.create(tmp_path / "s")
    _record(session, 4)
    before = [
        {k: e[k] for k in ("file", "episode_id", "status", "length")} for e in session.entries
    ]
    manifest = tmp_path / "s" / MANIFEST
    manifest.write_bytes(manifest.read_bytes()[: manifest.stat().st_size // 2])
    damaged = Session(tmp_path / "s")
    assert "damaged" in damaged.problems[0] and len(damaged.readable_paths()) == 4
    with pytest.warns(DataWarning, match="damaged"):
        episodes, count = open_episodes(tmp_path / "s")
    assert count == 4 and len(list(episodes)) == 4
    report = repair_session(tmp_path / "s")
    assert report.manifest_was == "damaged" and report.episodes == 4
    repaired = Session(tmp_path / "s")
    assert not repaired.problems
    after = [
        {k: e[k] for k in ("file", "episode_id", "status", "length")} for e in repaired.entries
    ]
    assert after == before


def test_repair_adopts_orphans_reports_missing_and_recovers_an_unfinished_episode(tmp_path):
    session = Session.create(tmp_path / "s")
    paths = _record(session, 3)
    paths[1].unlink()  # a file lost
    orphan = tmp_path / "s" / "episodes" / "000007_orphan.mcap"
    write_episode(orphan, length=5)
    unfinished = session.record(make_meta())  # a recorder that died mid-episode
    rng = np.random.default_rng(1)
    for t in range(25):
        unfinished.append(make_step(t, 25, rng, cameras=()))
    unfinished._writer.flush()
    unfinished._file.flush()
    manifest = json.loads((tmp_path / "s" / MANIFEST).read_text())
    dead = subprocess.Popen(["true"])
    dead.wait()
    manifest["episodes"][-1]["recorder"] = f"{socket.gethostname()}-{dead.pid}"  # died
    (tmp_path / "s" / MANIFEST).write_text(json.dumps(manifest))
    session.refresh()
    assert any("missing" in p for p in session.problems)
    assert any("not in the manifest" in p for p in session.problems)
    assert any("recorder stopped" in p for p in session.problems)
    assert len(session.readable_paths()) == 3  # the finished ones, the orphan among them
    report = repair_session(tmp_path / "s")
    assert report.missing == [f"episodes/{paths[1].name}"]
    assert report.adopted == ["episodes/000007_orphan.mcap"]
    assert report.recovered == [f"episodes/{unfinished.path.name}"]
    repaired = Session(tmp_path / "s")
    assert not repaired.problems and len(repaired.readable_paths()) == 4
    assert (tmp_path / "s" / "damaged" / unfinished.path.name).is_file()  # nothing deleted
    assert len(read_episode(unfinished.path, images=False)) >= 20  # at most a chunk lost
    running = session.record(make_meta())  # its recorder (this process) is alive
    running.append(make_step(0, 5, rng, cameras=()))
    assert repair_session(tmp_path / "s").busy == [
        f"episodes/{running.path.name} (process {socket.gethostname()}-{os.getpid()})"
    ]
    assert running.path.is_file()  # left alone


def test_a_recorder_killed_while_finishing_leaves_no_listed_episode_unreadable(tmp_path):
    """The end record goes into the file before its last chunk of steps and its summary:
    a kill anywhere in between leaves an end record in a file that is not whole, which
    must neither be listed as finished nor hide its steps from repair."""
    session = Session.create(tmp_path / "s")
    (path,) = _record(session, 1, length=15)
    whole = path.read_bytes()
    end_record = whole.find(mcap_log.META_END.encode())
    assert 0 < end_record < len(whole) - 100
    manifest = json.loads((tmp_path / "s" / MANIFEST).read_text())
    manifest["episodes"][0].update(status="recording")  # its entry was never updated
    manifest["episodes"][0].pop("length")
    cuts = range(end_record, len(whole), max(1, (len(whole) - end_record) // 25))
    for cut in cuts:
        (tmp_path / "s" / MANIFEST).write_text(json.dumps(manifest))
        path.write_bytes(whole[:cut])
        for file in Session(tmp_path / "s").readable_paths():
            assert len(read_episode(file, images=False)) == 15, f"cut at {cut}"
    assert len(cuts) > 10
    report = repair_session(tmp_path / "s")
    assert report.recovered == [f"episodes/{path.name}"]
    assert len(read_episode(path, images=False)) >= 1


def test_files_take_their_permissions_from_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        session = Session.create(tmp_path / "s")
        path = _record(session, 1)[0]
    finally:
        os.umask(old)
    assert (tmp_path / "s" / MANIFEST).stat().st_mode & 0o777 == 0o644
    assert path.stat().st_mode & 0o777 == 0o644


class FullDisk:
    """A file object that fails with ENOSPC once ``room`` bytes were written."""

    def __init__(self, file, room: int, error: int = errno.ENOSPC) -> None:
        self.file, self.room, self.error = file, room, error

    def write(self, data) -> int:
        if self.room < len(data):
            raise OSError(self.error, os.strerror(self.error))
        self.room -= len(data)
        return self.file.write(data)

    def __getattr__(self, name):
        return getattr(self.file, name)


@pytest.mark.parametrize(
    ("error", "said"), [(errno.ENOSPC, "is full"), (errno.EIO, "Input/output error")]
)
def test_a_failed_write_mid_episode_keeps_what_was_written_as_a_partial_episode(
    tmp_path, monkeypatch, error, said
):
    session = Session.create(tmp_path / "s")
    _record(session, 2)
    real_fdopen = os.fdopen

    def fdopen(fd, mode):  # episode files only: the manifest still has room
        episode = os.readlink(f"/proc/self/fd/{fd}").endswith(".mcap")
        return FullDisk(real_fdopen(fd, mode), 30_000, error) if episode else real_fdopen(fd, mode)

    monkeypatch.setattr(mcap_log.os, "fdopen", fdopen)
    recorder = Recorder(session, flush_seconds=0.1)
    recorder.start_episode(make_meta())
    rng = np.random.default_rng(0)
    with pytest.raises(DataError, match=f"{said}.*; the .* steps written so far are kept"):
        for t in range(1000):
            recorder.add_frame(make_step(t, 1000, rng, cameras=()))
    monkeypatch.undo()
    session.refresh()
    statuses = [e["status"] for e in session.entries]
    assert statuses == ["complete", "complete", "partial"]
    assert not list((tmp_path / "s").glob(".*.tmp"))
    assert len(session.readable_paths()) == 2
    report = repair_session(tmp_path / "s")
    assert len(report.recovered) == 1 and report.episodes == 3


def test_a_manifest_write_that_fails_leaves_no_temporary_file(tmp_path, monkeypatch):
    session = Session.create(tmp_path / "s")

    def no_space(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomic.os, "fsync", no_space)
    with pytest.raises(DataError, match="is full; free some space"):
        session.register(write_and_place(tmp_path / "s"), make_meta(), 12)
    monkeypatch.undo()
    assert not list((tmp_path / "s").glob(".*.tmp"))
    assert Session(tmp_path / "s").entries == []


def write_and_place(folder: Path) -> Path:
    path = folder / "episodes" / "000000_placed.mcap"
    write_episode(path)
    return path


def test_an_episode_is_refused_without_free_space_saying_how_much(tmp_path):
    session = Session(Session.create(tmp_path / "s").path, min_free=2**60)
    with pytest.raises(DataError, match=r"only \d+ MiB are free .* needs at least"):
        session.record(make_meta())
    assert Session(tmp_path / "s").entries == []


def test_no_damaged_episode_is_read_as_good(tmp_path):
    """Seeded random damage (byte flips, overwritten runs, cuts): every copy either reads
    exactly as recorded or is refused with the project's error."""
    path = tmp_path / "episode.mcap"
    write_episode(path, length=20)
    good = read_episode(path)
    data = path.read_bytes()
    rng = np.random.default_rng(7)
    refused = same = 0
    for case in range(300):
        damaged = bytearray(data)
        kind = case % 3
        at = int(rng.integers(len(data)))
        if kind == 0:
            damaged[at] ^= 1 << int(rng.integers(8))
        elif kind == 1:
            damaged[at : at + 16] = rng.integers(0, 256, 16, dtype=np.uint8).tobytes()
        else:
            damaged = damaged[:at]
        copy = tmp_path / "copy.mcap"
        copy.write_bytes(bytes(damaged))
        try:
            read = read_episode(copy)
        except McapError:
            refused += 1
            continue
        assert read.meta == good.meta, f"case {case}: damaged metadata read as good"
        for key, values in good.data.items():
            np.testing.assert_array_equal(read.data[key], values, err_msg=f"case {case}")
        for camera, frames in good.images.items():
            np.testing.assert_array_equal(read.images[camera], frames, err_msg=f"case {case}")
        same += 1
    assert refused + same == 300 and refused > 250


def test_a_corrupt_record_length_that_skips_the_data_end_is_refused(tmp_path):
    """One flipped bit in a record's length can make a reader jump over the rest of the
    data section (steps, the end record and the checksum) straight onto the summary."""
    from mcap.records import DataEnd
    from mcap.stream_reader import StreamReader

    path = tmp_path / "episode.mcap"
    write_episode(path, length=20)
    data = bytearray(path.read_bytes())
    ends, names = [], []
    with open(path, "rb") as stream:
        for record in StreamReader(stream, emit_chunks=True).records:
            ends.append(stream.tell())
            names.append(type(record).__name__)
    record = ends[names.index("Chunk")]  # the record after the first chunk
    summary = ends[names.index(DataEnd.__name__)]  # where the summary section begins
    data[record + 1 : record + 9] = (summary - record - 9).to_bytes(8, "little")
    path.write_bytes(bytes(data))
    with pytest.raises(McapError, match="data section does not end as written.*data recover"):
        read_episode(path)


def test_a_damaged_chunk_is_named_with_its_time_span_and_recovered_around(tmp_path):
    path = tmp_path / "episode.mcap"
    write_episode(path, length=40, flush_seconds=0.5)
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(McapError, match=r"damaged: the steps logged from [\d.]+ s to [\d.]+ s"):
        read_episode(path)
    assert verify(path).problems
    result = twinrl("data", "recover", str(path))
    assert result.returncode == 0 and "damaged chunks" in result.stdout, result.stderr
    recovered = read_episode(path.with_suffix(".recovered.mcap"), images=False)
    assert 0 < len(recovered) < 40


def test_verify_and_repair_on_the_command_line(tmp_path):
    session = Session.create(tmp_path / "s")
    paths = _record(session, 2)
    clean = twinrl("data", "verify", str(tmp_path / "s"))
    assert clean.returncode == 0 and "2 files checked, 0 problems" in clean.stdout
    data = bytearray(paths[0].read_bytes())
    data[len(data) // 2] ^= 0xFF
    paths[0].write_bytes(bytes(data))
    broken = twinrl("data", "verify", str(tmp_path / "s"))
    assert broken.returncode == 1 and "damaged" in broken.stdout
    (tmp_path / "s" / MANIFEST).write_text("{not json")
    listed = twinrl("data", "export", str(tmp_path / "s"), "--to", str(tmp_path / "d"))
    assert "warning:" in listed.stderr and "damaged" in listed.stderr
    repaired = twinrl("data", "repair", str(tmp_path / "s"))
    assert repaired.returncode == 0 and "manifest was damaged" in repaired.stdout
    assert json.loads((tmp_path / "s" / MANIFEST).read_text())["episodes"]
    folder = twinrl("data", "recover", str(tmp_path / "s"))
    assert folder.returncode == 2 and "is a folder" in folder.stderr


EXPORTER = """
    import sys
    from twinrl_data.lerobot_io import export_dataset
    from twinrl_data.sources import open_episodes
    episodes, _ = open_episodes(sys.argv[1], images=False)
    def slow(episode):
        print("episode", flush=True)
    export_dataset(episodes, sys.argv[2], on_episode=slow)
"""


@pytest.mark.slow
def test_a_killed_export_leaves_nothing_at_its_path_and_reruns_without_force(tmp_path):
    session = Session.create(tmp_path / "s")
    _record(session, 12, length=30)
    to = tmp_path / "dataset"
    proc = _python(EXPORTER, str(tmp_path / "s"), str(to))
    assert proc.stdout.readline().strip() == "episode"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not to.exists()
    again = twinrl("data", "export", str(tmp_path / "s"), "--to", str(to))
    assert again.returncode == 0, again.stderr
    assert not list(tmp_path.glob("dataset.partial-*"))
    assert verify(to).problems == []


def test_an_export_that_fails_leaves_the_old_path_as_it_was(tmp_path):
    from twinrl_data.lerobot_io import export_dataset

    session = Session.create(tmp_path / "s")
    _record(session, 3)
    to = tmp_path / "dataset"

    def fail(episode):
        raise RuntimeError("interrupted")

    episodes, _ = open_episodes(tmp_path / "s", images=False)
    with pytest.raises(RuntimeError):
        export_dataset(episodes, to, on_episode=fail)
    assert not to.exists() and not list(tmp_path.glob("dataset.partial-*"))
    episodes, _ = open_episodes(tmp_path / "s", images=False)
    export_dataset(episodes, to)
    assert verify(to).problems == []


@pytest.fixture
def small_disk(tmp_path):
    """A 3 MiB tmpfs (skipped where this machine may not mount one)."""
    mount = tmp_path / "disk"
    mount.mkdir()
    made = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=3m", "tmpfs", str(mount)], capture_output=True
    )
    if made.returncode != 0:
        pytest.skip("cannot mount a tmpfs here: " + made.stderr.decode().strip())
    yield mount
    subprocess.run(["umount", str(mount)], check=True)


def test_recording_until_a_real_disk_is_full(small_disk):
    session = Session(Session.create(small_disk / "s").path, min_free=0)
    rng = np.random.default_rng(0)
    recorder = Recorder(session, image_format="png", flush_seconds=0.2)
    with pytest.raises(DataError, match="is full") as error:
        while True:
            recorder.start_episode(make_meta())
            for t in range(20):
                noise = rng.integers(0, 256, (128, 128, 3), dtype=np.uint8)  # incompressible
                recorder.add_frame(
                    make_step(t, 20, rng, cameras=()) | {"observation.images.front": noise}
                )
            recorder.save_episode()
    assert "\n" not in str(error.value)
    session.refresh()
    finished = session.readable_paths()
    assert finished, "the disk held at least one episode"
    for path in finished:
        assert len(read_episode(path)) == 20
    assert not list((small_disk / "s").glob(".*.tmp"))


def test_a_read_only_session_is_read_and_refuses_a_recording_in_one_line(small_disk):
    session = Session(Session.create(small_disk / "s").path, min_free=0)
    _record(session, 2)
    subprocess.run(["mount", "-o", "remount,ro", str(small_disk)], check=True)
    try:
        reread = Session(small_disk / "s", min_free=0)
        assert [len(read_episode(p)) for p in reread.readable_paths()] == [6, 6]
        with pytest.raises(DataError, match="Read-only file system") as error:
            reread.record(make_meta())
        assert "\n" not in str(error.value)
    finally:
        subprocess.run(["mount", "-o", "remount,rw", str(small_disk)], check=True)


def _rtde_csv(rows: int, rng: np.random.Generator) -> str:
    from twinrl_data.importers import RTDE_MAP

    columns = [RTDE_MAP.time, *RTDE_MAP.commanded, *RTDE_MAP.measured, *RTDE_MAP.velocity]
    columns += [*RTDE_MAP.effort, *RTDE_MAP.tcp]
    lines = [" ".join(columns)]
    for t in range(rows):
        q = np.sin(0.05 * t + np.arange(6))
        values = [t * 0.008, *q, *(q + 1e-4), *np.cos(0.05 * t + np.arange(6))]
        values += [*rng.normal(size=6), 0.4, 0.1, 0.3, 0.0, 3.1, 0.0]
        lines.append(" ".join(f"{v:.6f}" for v in values))
    return "\n".join(lines) + "\n"


def test_no_damaged_csv_log_imports_to_non_finite_data(tmp_path):
    """Seeded damage to an RTDE CSV log (a cell made NaN, inf, 1e308, text or empty; a
    line cut): each import is refused with the project's error or gives finite data."""
    from twinrl_data.errors import TwinrlError
    from twinrl_data.importers import import_csv

    rng = np.random.default_rng(5)
    lines = _rtde_csv(60, rng).splitlines()
    refused = imported = 0
    for _ in range(150):
        damaged = [line.split(" ") for line in lines]
        row = int(rng.integers(len(damaged)))
        if rng.random() < 0.2:
            damaged[row] = damaged[row][: int(rng.integers(len(damaged[row])))]
        else:
            column = int(rng.integers(len(damaged[row])))
            damaged[row][column] = ["nan", "inf", "-inf", "1e308", "abc", ""][int(rng.integers(6))]
        path = tmp_path / "log.csv"
        path.write_text("\n".join(" ".join(cells) for cells in damaged) + "\n")
        try:
            episode = import_csv(path)
        except TwinrlError:
            refused += 1
            continue
        assert all(np.isfinite(values).all() for values in episode.data.values())
        imported += 1
    assert refused + imported == 150 and refused > 0


def test_verify_finds_any_damaged_file_of_an_exported_dataset(tmp_path):
    from twinrl_data.lerobot_io import export_dataset, verify_dataset

    _record(Session.create(tmp_path / "s"), 2)
    export_dataset(open_episodes(tmp_path / "s", images=False)[0], tmp_path / "d")
    assert verify_dataset(tmp_path / "d")[1] == []
    rng = np.random.default_rng(2)
    files = sorted(p for p in (tmp_path / "d").rglob("*") if p.is_file())
    for file in files:
        original = file.read_bytes()
        damaged = bytearray(original)
        damaged[int(rng.integers(len(damaged)))] ^= 0x20
        file.write_bytes(bytes(damaged))
        assert verify_dataset(tmp_path / "d")[1], f"damage to {file.name} went unseen"
        file.write_bytes(original)


def test_no_damaged_column_map_gives_anything_but_one_clear_error_or_finite_data(tmp_path):
    """Seeded damage to a column map (a value replaced by NaN, inf, a huge number, a
    wrong type, a missing column; a key renamed): loading and importing either fail
    with the project's error or give finite data."""
    import yaml

    from twinrl_data.errors import TwinrlError
    from twinrl_data.importers import RTDE_MAP, ColumnMap, import_csv

    rng = np.random.default_rng(9)
    log = tmp_path / "log.csv"
    log.write_text(_rtde_csv(40, rng))
    good = {
        "time": RTDE_MAP.time,
        "rate": 125,
        "commanded": RTDE_MAP.commanded,
        "measured": RTDE_MAP.measured,
        "velocity": RTDE_MAP.velocity,
        "tcp": RTDE_MAP.tcp,
        "time_unit": "s",
        "angle_unit": "rad",
    }
    bad_values = [float("nan"), float("inf"), 1e300, -5, "x", [], None, ["nope"] * 6, {"a": 1}]
    refused = imported = 0
    for _ in range(150):
        data = dict(good)
        key = list(data)[int(rng.integers(len(data)))]
        if rng.random() < 0.15:
            data[key + "_typo"] = data.pop(key)
        else:
            data[key] = bad_values[int(rng.integers(len(bad_values)))]
        path = tmp_path / "map.yaml"
        path.write_text(yaml.safe_dump(data))
        try:
            episode = import_csv(log, ColumnMap.load(path))
        except TwinrlError:
            refused += 1
            continue
        assert all(np.isfinite(v).all() for v in episode.data.values() if v.dtype.kind == "f")
        imported += 1
    assert refused + imported == 150 and refused > 100
