"""Episodes to and from LeRobotDataset v3, through lerobot's own API.

Export writes with ``LeRobotDataset.create`` / ``add_frame`` / ``save_episode`` /
``finalize`` (cameras as videos). What a LeRobotDataset has no place for, the episode
metadata (source, world, region, config, twin digest, policy, success, interventions,
...), goes to a sidecar beside lerobot's own metadata, one JSON line per episode::

    DATASET/
      meta/info.json, meta/episodes/..., meta/tasks.parquet, meta/stats.json   (lerobot)
      meta/twinrl/episodes.jsonl          {"episode_index": 0, "task": ..., "source": ...}
      meta/twinrl/live.json               what a row of live episodes holds (if any)
      data/chunk-000/file-000.parquet                                          (lerobot)
      videos/observation.images.front/chunk-000/file-000.mp4                   (lerobot)

A live episode (every camera frame and the controller's state at their own rates) is
exported at its cameras' rate, its videos as they were encoded while recording
(:mod:`twinrl_data.live_export` says what each row holds).

Import reads any LeRobotDataset (twinrl's or one recorded with lerobot's tools) back
into episodes; contract fields the dataset lacks are reported, not invented.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from twinrl_data import schema as contract
from twinrl_data.atomic import publishing, write_text_atomic
from twinrl_data.errors import DataError
from twinrl_data.live_export import (
    LIVE_INFO,
    LiveRows,
    LiveVideos,
    decode_frame,
    encoder_config,
    live_dataset_class,
    live_info,
    video_stats,
)

SIDECAR = Path("meta") / "twinrl" / "episodes.jsonl"
CHECKSUMS = Path("meta") / "twinrl" / "files.json"  # sha256 of every file, at export
ACTION_NAMES = ["dx", "dy", "dz", "rx", "ry", "rz", "gripper"]
VIDEO_BACKEND = "pyav"  # decodes everywhere, also without a system FFmpeg
# Encode camera streams in background threads while frames are added (about twice as
# fast as encoding after each episode on two cores). lerobot drops a frame when the
# encoder's queue is full, so the queue is made long enough never to be.
WRITE_OPTIONS = {
    "use_videos": True,
    "video_backend": VIDEO_BACKEND,
    "streaming_encoding": True,
    "encoder_queue_maxsize": 100_000,
}


def _lerobot():
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset


def features_for(episode: contract.Episode | LiveRows) -> dict[str, dict[str, Any]]:
    """LeRobot feature spec of an episode's fields (vectors, flags, camera videos)."""
    if isinstance(episode, LiveRows):
        features = features_for(episode.episode)
        for camera in episode.frames:
            features[contract.image_field(camera)] = {
                "dtype": "video",
                "shape": episode.shape(camera),
                "names": ["height", "width", "channels"],
            }
        return features
    features: dict[str, dict[str, Any]] = {}
    for key in contract.VECTOR_FIELDS:
        if key in episode.data:
            width = episode.data[key].shape[1]
            names = episode.meta.names.get(key) or (
                ACTION_NAMES if key.startswith("action") else None
            )
            if names is None or len(names) != width:
                names = [f"{key}.{i}" for i in range(width)]
            features[key] = {"dtype": "float32", "shape": (width,), "names": list(names)}
    for key, dtype in (
        (contract.INTERVENTION, "bool"),
        (contract.REWARD, "float32"),
        (contract.DONE, "bool"),
        (contract.SUCCESS, "bool"),
    ):
        if key in episode.data:
            features[key] = {"dtype": dtype, "shape": (1,), "names": None}
    for camera, frames in episode.images.items():
        height, width = frames.shape[1:3]
        features[contract.image_field(camera)] = {
            "dtype": "video",
            "shape": (height, width, 3),
            "names": ["height", "width", "channels"],
        }
    return features


def _same_features(a: dict[str, dict[str, Any]], b: dict[str, dict[str, Any]]) -> str | None:
    if set(a) != set(b):
        return f"fields differ: {sorted(set(a) ^ set(b))}"
    for key in a:
        first = f"{a[key]['dtype']}{tuple(a[key]['shape'])}"
        other = f"{b[key]['dtype']}{tuple(b[key]['shape'])}"
        if first != other:
            return f"{key}: {first} vs {other}"
    return None


@dataclass(frozen=True)
class ExportResult:
    root: Path
    repo_id: str
    episodes: int
    frames: int


def export_dataset(
    episodes: Iterable[contract.Episode | LiveRows],
    to: str | Path,
    *,
    repo_id: str | None = None,
    force: bool = False,
    on_episode: Callable[[contract.Episode], None] | None = None,
) -> ExportResult:
    """Write ``episodes`` (all with the same fields, shapes and rate) as one LeRobotDataset;
    a live episode's :class:`~twinrl_data.live_export.LiveRows` at its cameras' rate.

    ``to`` must not exist unless ``force`` (then it is replaced). Raises
    :class:`~twinrl_data.errors.DataError` when episodes disagree on their fields.
    """
    root = Path(to)
    if root.exists() and not force:
        raise DataError(f"{root} already exists; choose another folder or replace it (`force`)")
    iterator = iter(episodes)
    first = next(iterator, None)
    if first is None:
        raise DataError("nothing to export: the selection has no episodes")
    repo_id = repo_id or f"twinrl/{root.name}"
    # Built beside ``root`` and renamed into place at the end: a killed export leaves
    # ``root`` as it was (absent, or the old dataset), never half a dataset.
    with publishing(root) as building:
        count, frames = _write(building, repo_id, first, iterator, on_episode)
        _write_checksums(building)
        if root.exists():
            shutil.rmtree(root)  # replaced (``force``) only once the new one is whole
    return ExportResult(root=root, repo_id=repo_id, episodes=count, frames=frames)


def _checksums(root: Path) -> dict[str, str]:
    """The sha256 of every file under ``root`` but the checksum file itself."""
    sums = {}
    for file in sorted(p for p in root.rglob("*") if p.is_file()):
        relative = file.relative_to(root).as_posix()
        if relative != CHECKSUMS.as_posix():
            sums[relative] = hashlib.sha256(file.read_bytes()).hexdigest()
    return sums


def _write_checksums(root: Path) -> None:
    write_text_atomic(root / CHECKSUMS, json.dumps(_checksums(root), indent=1))


def _write(
    root: Path,
    repo_id: str,
    first: contract.Episode | LiveRows,
    rest: Iterable[contract.Episode | LiveRows],
    on_episode: Callable[[contract.Episode], None] | None,
) -> tuple[int, int]:
    """Write ``first`` and ``rest`` as a new LeRobotDataset at ``root``: (episodes, frames)."""
    features = features_for(first)
    fps = round(_episode(first).meta.fps)
    live = LiveVideos() if isinstance(first, LiveRows) else None
    create = live_dataset_class(live).create if live is not None else _lerobot().create
    dataset = create(
        repo_id=repo_id,
        fps=fps,
        features=features,
        root=root,
        robot_type=_episode(first).meta.robot,
        **WRITE_OPTIONS,
        **({"rgb_encoder": encoder_config()} if live is not None else {}),
    )
    sidecar = root / SIDECAR
    sidecar.parent.mkdir(parents=True, exist_ok=True)
    count = frames = 0
    try:
        with open(sidecar, "w") as lines:
            for item in _chain(first, rest):
                episode = _episode(item)
                mismatch = _same_features(features, features_for(item))
                if round(episode.meta.fps) != fps:
                    mismatch = f"{episode.meta.fps:g} fps, the first {fps} fps"
                if mismatch:
                    raise DataError(
                        f"episode {episode.meta.episode_id} does not match the first one "
                        f"({mismatch}); export episodes of one task and recorder together "
                        "(a live episode exports at its cameras' rate)"
                    )
                if isinstance(item, LiveRows) and live is not None:
                    _add_live(dataset, item, live)
                else:
                    _add_episode(dataset, episode)
                lines.write(json.dumps({"episode_index": count, **episode.meta.to_dict()}) + "\n")
                count += 1
                frames += len(item)
                if on_episode is not None:
                    on_episode(episode)
    finally:
        dataset.finalize()
    if isinstance(first, LiveRows):
        write_text_atomic(root / LIVE_INFO, json.dumps(live_info(first), indent=1))
    return count, frames


def _episode(item: contract.Episode | LiveRows) -> contract.Episode:
    return item.episode if isinstance(item, LiveRows) else item


def _chain(first: Any, rest: Iterable[Any]) -> Iterable[Any]:
    yield first
    yield from rest


def _fields(episode: contract.Episode, t: int) -> dict[str, Any]:
    """Row ``t`` of an episode's vector and scalar fields, as lerobot's frame holds them."""
    frame: dict[str, Any] = {"task": episode.meta.instruction or episode.meta.task}
    for key in contract.VECTOR_FIELDS:
        if key in episode.data:
            frame[key] = episode.data[key][t].astype(np.float32)
    for key in contract.SCALAR_FIELDS:
        if key in episode.data:
            dtype = np.float32 if key == contract.REWARD else bool
            frame[key] = np.array([episode.data[key][t]], dtype=dtype)
    return frame


def _add_episode(dataset: Any, episode: contract.Episode) -> None:
    for t in range(len(episode)):
        frame = _fields(episode, t)
        for camera, frames in episode.images.items():
            frame[contract.image_field(camera)] = frames[t]
        dataset.add_frame(frame)
    dataset.save_episode()


def _add_live(dataset: Any, rows: LiveRows, videos: LiveVideos) -> None:
    """A live episode's rows; its videos its logged frames remuxed (a log from before the
    frames were H.264 has JPEGs: they are encoded here)."""
    encoded = set(rows.videos) == set(rows.frames)
    videos.use(
        {
            contract.image_field(camera): (rows.videos[camera], video_stats(rows.frames[camera]))
            for camera in rows.frames
        }
        if encoded
        else None
    )
    blank = {camera: np.zeros(rows.shape(camera), np.uint8) for camera in rows.frames}
    for t in range(len(rows)):
        frame = _fields(rows.episode, t)
        for camera, logged in rows.frames.items():
            image = blank[camera] if encoded else decode_frame(logged[t])
            frame[contract.image_field(camera)] = image
        dataset.add_frame(frame)
    dataset.save_episode()


def read_sidecar(root: str | Path) -> dict[int, dict[str, Any]]:
    """Episode metadata written by :func:`export_dataset`, by episode index (may be empty)."""
    path = Path(root) / SIDECAR
    if not path.is_file():
        return {}
    rows = {}
    for line in path.read_text().splitlines():
        if line.strip():
            row = json.loads(line)
            rows[int(row.pop("episode_index"))] = row
    return rows


def open_dataset(root: str | Path, **kwargs: Any) -> Any:
    """A plain ``lerobot`` LeRobotDataset read from ``root`` (offline, PyAV decoding)."""
    root = Path(root)
    if not (root / "meta" / "info.json").is_file():
        raise DataError(f"{root} is not a LeRobotDataset (no meta/info.json)")
    try:
        return _lerobot()(
            repo_id=f"local/{root.name}", root=root, video_backend=VIDEO_BACKEND, **kwargs
        )
    except Exception as err:
        raise DataError(
            f"{root} could not be opened as a LeRobotDataset ({type(err).__name__}: {err})"
        ) from None


@dataclass(frozen=True)
class ImportReport:
    """What an import found: the contract fields the dataset did not have."""

    episodes: int
    missing_fields: tuple[str, ...]
    cameras: tuple[str, ...]


def missing_contract_fields(features: dict[str, Any]) -> list[str]:
    wanted = [*contract.VECTOR_FIELDS, *contract.SCALAR_FIELDS]
    return [key for key in wanted if key not in features]


def iter_dataset_episodes(
    root: str | Path,
    *,
    source: str = "teleop",
    world: str = "real",
    episodes: list[int] | None = None,
    cameras: Sequence[str] | None = None,
) -> Iterable[contract.Episode]:
    """Episodes of a LeRobotDataset, in index order; fields it lacks stay absent.

    ``cameras`` limits which camera videos are decoded (``None``: all, ``[]``: none).

    twinrl's sidecar metadata is used when present; otherwise ``source`` and ``world``
    describe where the data came from and the task is the dataset's task text.
    """
    from lerobot.datasets.video_utils import decode_video_frames

    dataset = open_dataset(root)
    meta = dataset.meta
    sidecar = read_sidecar(root)
    if contract.STATE not in meta.features or contract.ACTION not in meta.features:
        raise DataError(
            f"{root} does not follow the episode contract: it lacks "
            f"{[k for k in (contract.STATE, contract.ACTION) if k not in meta.features]} "
            f"(it has {sorted(meta.features)})"
        )
    # Every column read in one batch: per-episode access to a formatted dataset converts
    # row by row and took seconds per hundred episodes.
    wanted = [
        k for k in (*contract.VECTOR_FIELDS, *contract.SCALAR_FIELDS) if k in meta.features
    ] + ["timestamp", "task_index", "episode_index"]
    columns = dataset.hf_dataset.select_columns(wanted).with_format("numpy")[:]
    episode_column = np.asarray(columns["episode_index"])
    indices = episodes if episodes is not None else list(range(meta.total_episodes))
    video_keys = [k for k, ft in meta.features.items() if ft["dtype"] == "video"]
    if cameras is not None:
        video_keys = [k for k in video_keys if k.removeprefix(contract.IMAGES_PREFIX) in cameras]
    for index in indices:
        rows = np.flatnonzero(episode_column == index)
        if len(rows) == 0:
            raise DataError(f"{root} has no episode {index} (it has {meta.total_episodes})")
        part = {key: values[rows] for key, values in columns.items()}
        data: dict[str, np.ndarray] = {}
        for key in (*contract.VECTOR_FIELDS, *contract.SCALAR_FIELDS):
            if key in meta.features:
                values = np.asarray(part[key])
                if key in contract.SCALAR_FIELDS:
                    values = values.reshape(len(rows)).astype(
                        np.float32 if key == contract.REWARD else bool
                    )
                else:  # (n, width), a width-1 vector too, which the columns flatten
                    values = values.reshape(len(rows), -1).astype(np.float32)
                data[key] = values
        timestamps = [float(t) for t in np.asarray(part["timestamp"])]
        images = {}
        for key in video_keys:
            record = meta.episodes[index]
            offset = float(record[f"videos/{key}/from_timestamp"])
            path = Path(root) / meta.get_video_file_path(index, key)
            frames = decode_video_frames(
                path,
                [offset + t for t in timestamps],
                dataset.tolerance_s,
                VIDEO_BACKEND,
                return_uint8=True,
            )
            images[key.removeprefix(contract.IMAGES_PREFIX)] = frames.permute(0, 2, 3, 1).numpy()
        episode_meta = episode_metadata(
            meta, sidecar, index, int(np.asarray(part["task_index"])[0]), source=source, world=world
        )
        yield contract.Episode(meta=episode_meta, data=data, images=images)


def episode_metadata(
    meta: Any,
    sidecar: dict[int, dict[str, Any]],
    index: int,
    task_index: int,
    *,
    source: str,
    world: str,
) -> contract.EpisodeMeta:
    """twinrl's metadata of a dataset episode: from the sidecar, else from what lerobot
    stores (task text, fps, robot type, feature names) plus the given source and world."""
    if index in sidecar:
        return contract.EpisodeMeta.from_dict(sidecar[index])
    task_text = str(meta.tasks.index[task_index]) if meta.tasks is not None else "unknown"
    names = {
        k: list(meta.features[k].get("names") or [])
        for k in contract.VECTOR_FIELDS
        if k in meta.features
    }
    return contract.EpisodeMeta(
        task=task_text,
        instruction=task_text,
        source=source,
        world=world,
        fps=float(meta.fps),
        robot=meta.robot_type or "unknown",
        names=names,
    )


def verify_dataset(root: str | Path) -> tuple[int, list[str]]:
    """Check a LeRobot dataset folder: (files checked, problems one line each).

    Every file matches the checksum recorded when twinrl exported it (where it did);
    its metadata parses and lerobot opens it; the data files' rows add up to the frames
    and episodes its metadata declares; twinrl's sidecar has one line per episode; every
    video file decodes its first frame.
    """
    import av
    import pyarrow.parquet as pq

    root = Path(root)
    problems: list[str] = []
    try:
        info = json.loads((root / "meta" / "info.json").read_text())
    except (OSError, ValueError) as err:
        return 1, [f"{root}/meta/info.json cannot be read ({err})"]
    checked = 1
    rows, episodes = 0, set()
    for file in sorted((root / "data").rglob("*.parquet")):
        checked += 1
        try:
            table = pq.read_table(file, columns=["episode_index"])
        except Exception as err:
            problems.append(f"{file} cannot be read ({type(err).__name__}: {err})")
            continue
        rows += table.num_rows
        episodes.update(table.column("episode_index").to_pylist())
    if rows != info.get("total_frames"):
        problems.append(
            f"{root}: the data holds {rows} frames, meta/info.json says {info.get('total_frames')}"
        )
    if len(episodes) != info.get("total_episodes"):
        problems.append(
            f"{root}: the data holds {len(episodes)} episodes, meta/info.json says "
            f"{info.get('total_episodes')}"
        )
    sidecar = read_sidecar(root)
    if sidecar and len(sidecar) != info.get("total_episodes"):
        problems.append(
            f"{root}/{SIDECAR}: {len(sidecar)} lines for {info.get('total_episodes')} episodes"
        )
    for video in sorted((root / "videos").rglob("*.mp4")):
        checked += 1
        try:
            with av.open(str(video)) as container:
                next(container.decode(video=0))
        except Exception as err:
            problems.append(f"{video} does not decode ({type(err).__name__})")
    if (root / CHECKSUMS).is_file():
        try:
            recorded = json.loads((root / CHECKSUMS).read_text())
        except ValueError:
            recorded = {}
            problems.append(f"{root / CHECKSUMS} is damaged")
        found = _checksums(root)
        for relative, digest in recorded.items():
            if relative not in found:
                problems.append(f"{root}/{relative} is missing")
            elif found[relative] != digest:
                problems.append(f"{root}/{relative} changed since it was exported (checksum)")
    if not problems:
        try:
            open_dataset(root)
        except DataError as err:
            problems.append(str(err))
    return checked, problems
