"""Fault injection and fuzzing of the episode log, counted: the reliability page's table.

Runs, with seeds:

- recorders killed with SIGKILL at random points (one session, one kill after another);
- two and three recorders appending to one session at once;
- manifests damaged at random (bytes flipped, cut, replaced);
- episode files damaged at random (bits flipped, runs overwritten, cut);
- scene specs with one number replaced (NaN, infinities, 1e300, negatives, wrong types);
- LeRobot datasets with a data or metadata file damaged.

and counts the episodes lost (a finished episode no longer listed or readable) and the
damaged inputs read as good (accepted and returning something other than what was
written). The target for both is 0. Usage::

    python bench/bench_faults.py --kills 40 --damage 3000 --specs 2000 --datasets 30
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
import warnings
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.data.conftest import make_meta, make_step, write_episode  # noqa: E402
from tests.sim.test_spec import number_paths, replaced  # noqa: E402
from twinrl_data.errors import DataError, TwinrlError  # noqa: E402
from twinrl_data.lerobot_io import export_dataset, verify_dataset  # noqa: E402
from twinrl_data.mcap_log import read_episode, read_summary  # noqa: E402
from twinrl_data.recorder import Recorder  # noqa: E402
from twinrl_data.session import MANIFEST, Session  # noqa: E402
from twinrl_data.sources import open_episodes  # noqa: E402

RECORDER = """
    import sys
    import numpy as np
    from tests.data.conftest import make_meta, make_step
    from twinrl_data.recorder import Recorder
    from twinrl_data.session import Session
    recorder = Recorder(Session.create(sys.argv[1], exist_ok=True), flush_seconds=0.3)
    rng = np.random.default_rng(int(sys.argv[2]))
    for _ in range(int(sys.argv[3])):
        recorder.start_episode(make_meta())
        for t in range(15):
            recorder.add_frame(make_step(t, 15, rng, cameras=("front",)))
            print("frame", flush=True)
        recorder.save_episode()
"""


def _recorder(session: Path, seed: int, episodes: int) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(RECORDER), str(session), str(seed), str(episodes)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )


def _finished(session: Path) -> set[str]:
    """Files of the finished episodes that read whole."""
    good = set()
    for path in Session(session).readable_paths():
        if len(read_episode(path, images=False)) == read_summary(path).length:
            good.add(path.name)
    return good


def kills(folder: Path, count: int, rng: np.random.Generator) -> dict:
    session = folder / "killed"
    lost, finished = 0, set()
    for kill in range(count):
        proc = _recorder(session, kill, 1000)
        for _ in range(int(rng.integers(1, 60))):
            proc.stdout.readline()
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        now = _finished(session)
        lost += len(finished - now)
        finished = now
    return {"runs": count, "faults": count, "lost": lost, "episodes": len(finished)}


def writers(folder: Path, repeats: int) -> dict:
    lost = runs = 0
    for repeat in range(repeats):
        for n in (2, 3):
            session = folder / f"writers_{repeat}_{n}"
            Session.create(session)
            procs = [_recorder(session, i, 5) for i in range(n)]
            for proc in procs:
                proc.communicate()
            lost += 5 * n - len(_finished(session))
            runs += 1
    return {"runs": runs, "faults": runs, "lost": lost}


def _session(path: Path, episodes: int, length: int, cameras: tuple[str, ...]) -> Path:
    """A session of ``episodes`` finished episodes of ``length`` steps."""
    recorder = Recorder(Session.create(path))
    rng = np.random.default_rng(0)
    for _ in range(episodes):
        recorder.start_episode(make_meta())
        for t in range(length):
            recorder.add_frame(make_step(t, length, rng, cameras=cameras))
        recorder.save_episode()
    return path


def _damaged(original: bytes, case: int, rng: np.random.Generator, run: int) -> bytes:
    """``original`` with one seeded fault, by ``case``: a bit flipped, ``run`` bytes
    overwritten at random, or the rest cut off."""
    data = bytearray(original)
    at = int(rng.integers(len(data)))
    if case % 3 == 0:
        data[at] ^= 1 << int(rng.integers(8))
    elif case % 3 == 1:
        data[at : at + run] = rng.integers(0, 256, run, dtype=np.uint8).tobytes()
    else:
        data = data[:at]
    return bytes(data)


def manifests(folder: Path, count: int, rng: np.random.Generator) -> dict:
    session = _session(folder / "manifest", episodes=4, length=6, cameras=())
    original = (session / MANIFEST).read_bytes()
    lost = 0
    for case in range(count):
        (session / MANIFEST).write_bytes(_damaged(original, case, rng, run=8))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                episodes, _ = open_episodes(session, images=False)
                lost += 4 - len(list(episodes))
            except TwinrlError:
                lost += 4
    (session / MANIFEST).write_bytes(original)
    return {"runs": count, "inputs": count, "lost": lost}


def episodes(folder: Path, count: int, rng: np.random.Generator) -> dict:
    path = folder / "episode.mcap"
    write_episode(path, length=30, flush_seconds=0.5)
    good = read_episode(path)
    original = path.read_bytes()
    silent = refused = 0
    copy_path = folder / "damaged.mcap"
    for case in range(count):
        copy_path.write_bytes(_damaged(original, case, rng, run=16))
        try:
            read = read_episode(copy_path)
        except DataError:
            refused += 1
            continue
        same = read.meta == good.meta and all(
            np.array_equal(read.data[k], v) for k, v in good.data.items()
        )
        same = same and all(np.array_equal(read.images[c], f) for c, f in good.images.items())
        silent += not same
    return {"runs": count, "inputs": count, "refused": refused, "silent": silent}


def specs(count: int, rng: np.random.Generator) -> dict:
    from twinrl_sim.build import compile_scene
    from twinrl_sim.cell import Cell
    from twinrl_sim.spec import parse_spec
    from twinrl_sim.tasks import TASKS, make_task

    values = [float("nan"), float("inf"), -float("inf"), 1e300, -1e300, -1.0, 0.0, 1e6, "x", []]
    silent = refused = 0
    bases = {t: json.loads(make_task(t).scene.model_dump_json()) for t in TASKS}
    for case in range(count):
        base = bases[list(TASKS)[case % len(TASKS)]]
        paths = list(number_paths(base))
        path = paths[int(rng.integers(len(paths)))]
        data = replaced(base, path, values[int(rng.integers(len(values)))])
        try:
            cell = Cell(compile_scene(parse_spec(data)))
        except TwinrlError:
            refused += 1
            continue
        cell.reset_robot()
        for _ in range(5):
            cell.send(np.array(cell.layout.home_qpos), 0.0)
        silent += not np.isfinite(cell.state_vector()).all()
        cell.close()
    return {"runs": count, "inputs": count, "refused": refused, "silent": silent}


def datasets(folder: Path, count: int, rng: np.random.Generator) -> dict:
    source = _session(folder / "for_dataset", episodes=3, length=12, cameras=("front",))
    root = folder / "dataset"
    export_dataset(open_episodes(source)[0], root)
    files = [
        p for p in root.rglob("*") if p.is_file() and p.suffix in (".parquet", ".json", ".mp4")
    ]
    silent = 0
    for _ in range(count):
        target = files[int(rng.integers(len(files)))]
        original = target.read_bytes()
        data = bytearray(original)
        at = int(rng.integers(len(data)))
        data[at : at + 32] = rng.integers(0, 256, 32, dtype=np.uint8).tobytes()
        target.write_bytes(bytes(data))
        _, problems = verify_dataset(root)
        silent += not problems
        target.write_bytes(original)
    return {"runs": count, "inputs": count, "silent": silent}


def main(
    kills_count: Annotated[int, typer.Option("--kills", help="Recorders killed.")] = 40,
    writer_repeats: Annotated[
        int, typer.Option("--writers", help="Rounds of 2 and 3 writers.")
    ] = 3,
    manifest_count: Annotated[int, typer.Option("--manifests", help="Manifests damaged.")] = 300,
    damage: Annotated[int, typer.Option(help="Episode files damaged.")] = 3000,
    spec_count: Annotated[int, typer.Option("--specs", help="Scene specs fuzzed.")] = 2000,
    dataset_count: Annotated[int, typer.Option("--datasets", help="Dataset files damaged.")] = 30,
    seed: Annotated[int, typer.Option(help="Seeds every random choice.")] = 0,
) -> None:
    """Print the reliability table (Markdown)."""
    rng = np.random.default_rng(seed)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for name, run in (
            ("recorders killed (SIGKILL)", lambda: kills(folder, kills_count, rng)),
            ("2 and 3 concurrent recorders", lambda: writers(folder, writer_repeats)),
            ("damaged manifests", lambda: manifests(folder, manifest_count, rng)),
            ("damaged episode files", lambda: episodes(folder, damage, rng)),
            ("scene specs with a bad number", lambda: specs(spec_count, rng)),
            ("damaged LeRobot dataset files", lambda: datasets(folder, dataset_count, rng)),
        ):
            start = time.perf_counter()
            result = run()
            result["seconds"] = time.perf_counter() - start
            rows.append((name, result))
            print(f"{name}: {result}", file=sys.stderr, flush=True)
    print("| campaign | runs | episodes lost | damaged inputs read as good | refused | time |")
    print("|---|---|---|---|---|---|")
    for name, r in rows:
        print(
            f"| {name} | {r['runs']} | {r.get('lost', '-')} | {r.get('silent', '-')} | "
            f"{r.get('refused', '-')} | {r['seconds']:.0f} s |"
        )


if __name__ == "__main__":
    typer.run(main)
