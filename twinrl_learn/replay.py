"""Replay buffers as views over episodes.

A :class:`ReplayBuffer` holds whole episodes of the episode contract (demos,
interventions, RL rollouts) and indexes their steps for sampling; it is saved as a
LeRobotDataset and loaded from LeRobotDatasets or from logged episodes, so a buffer is
never a format of its own.

Sampling follows the policy's action chunks (Q-chunking): a transition from step ``t``
is the chunk of actions ``a[t : t+h]``, the discounted reward over those steps, and the
observation ``h`` steps later (or fewer at a successful episode's end or at a takeover,
both terminal). Steps whose chunk would run past the end of an unfinished episode (timeout,
no next observation logged) are not sampled.

Rewards are recomputed from each step's ``next.success`` with the learner's reward
settings (TwinRL: +10 on success, -0.05 per step), so data logged under other reward
settings stays usable. An operator's takeover ends the policy's stretch of the episode
(as in RLIF): its last step before the takeover is terminal and earns the ``takeover``
reward, so that the critic learns which of the policy's actions led to it; otherwise
the operator's success would be credited to them.

Rows whose action is a human's (demonstration episodes, intervention steps) are marked
``demo``: the imitation term of the actor learns from those only.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from twinrl_data.chunks import chunk_rows
from twinrl_data.lerobot_io import export_dataset, iter_dataset_episodes
from twinrl_data.schema import (
    ACTION,
    ENVIRONMENT_STATE,
    INTERVENTION,
    STATE,
    SUCCESS,
    Episode,
)
from twinrl_learn.errors import LearnError

DEMO_SOURCES = ("teleop", "twin_demo")  # episodes whose every action is a demonstration


@dataclass(frozen=True)
class RewardSettings:
    """Reward from success: ``success`` when the task is done, ``step`` otherwise;
    ``takeover`` is added on the policy's last step before an operator takes over,
    which ends the policy's stretch (``None``: the stretch runs on through the
    operator's steps)."""

    success: float = 10.0
    """Reward of the step that completes the task."""
    step: float = -0.05
    """Reward of every other step."""
    takeover: float | None = 0.0
    """Reward of the policy's last step before a takeover, which ends its stretch for the
    critic (a success earns 10); ending the stretch measured better than running on
    (docs/results/defaults.md)."""


# A pose estimator's rows for an episode's images (by camera) and states.
Estimate = Callable[[dict[str, np.ndarray], np.ndarray], np.ndarray]


@dataclass
class TransitionBatch:
    """Sampled chunked transitions (numpy, physical action units).

    ``actions`` (B, h, A); ``discount`` is gamma^n for the n steps the chunk covered, 0
    where the chunk ended the episode successfully; ``mc_return`` is the discounted
    return of the rest of the episode from the first step (Cal-QL's lower bound).
    """

    state: np.ndarray
    environment_state: np.ndarray | None
    images: dict[str, np.ndarray]
    instruction: list[str]
    actions: np.ndarray
    reward: np.ndarray
    discount: np.ndarray
    next_state: np.ndarray
    next_environment_state: np.ndarray | None
    next_images: dict[str, np.ndarray]
    mc_return: np.ndarray
    intervention: np.ndarray
    demo: np.ndarray  # the action is a human's (demonstration or intervention): BC data
    estimates: np.ndarray | None = None  # a pose estimator's view of the state (see estimate)
    next_estimates: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.state)


@dataclass
class ReplayBuffer:
    """Episodes plus flat per-step arrays for sampling; see the module docstring.

    ``capacity`` (steps) drops the oldest episodes first once exceeded; ``cameras``
    names the images kept (none for state policies). ``estimate`` (images by camera,
    states) -> rows is what a policy acting through a pose estimator reads of each step
    (:meth:`~twinrl_learn.perception.estimator.PoseEstimator.estimate_rows`): it is
    computed once per episode and sampled beside the images, so an update runs no image
    network.
    """

    cameras: tuple[str, ...] = ()
    capacity: int | None = None
    rewards: RewardSettings = field(default_factory=RewardSettings)
    episodes: list[Episode] = field(default_factory=list)
    estimate: Estimate | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        self._estimates: dict[int, np.ndarray] = {}  # id(episode) -> its rows' estimates
        self._arrays: dict[str, np.ndarray] = {}
        self._images: dict[str, np.ndarray] = {}
        self._instructions: list[str] = []
        self._built_for: float | None = None  # the gamma the arrays were built with
        self._starts: dict[int, np.ndarray] = {}  # valid starts per chunk length
        episodes, self.episodes = self.episodes, []
        self.extend(episodes)

    # ------------------------------------------------------------------ filling
    def add(self, episode: Episode) -> None:
        missing = [c for c in self.cameras if c not in episode.images]
        if missing:
            raise LearnError(
                f"episode {episode.meta.episode_id} has no camera(s) {missing} "
                f"(it has {episode.cameras}); record with images or use a state policy"
            )
        if SUCCESS not in episode.data:
            raise LearnError(
                f"episode {episode.meta.episode_id} has no next.success; a replay buffer "
                "needs the outcome of every step to compute rewards"
            )
        self.episodes.append(episode)
        if self.capacity is not None:
            while len(self.episodes) > 1 and self.num_steps > self.capacity:
                self._estimates.pop(id(self.episodes.pop(0)), None)
        self._built_for = None

    def extend(self, episodes: Iterable[Episode]) -> None:
        for episode in episodes:
            self.add(episode)

    @classmethod
    def from_datasets(
        cls, roots: Sequence[str | Path], *, cameras: Sequence[str] = (), **kwargs
    ) -> ReplayBuffer:
        """A buffer over the episodes of LeRobotDatasets (e.g. demos, a twin buffer)."""
        buffer = cls(cameras=tuple(cameras), **kwargs)
        for root in roots:
            buffer.extend(iter_dataset_episodes(root, cameras=list(cameras)))
        return buffer

    def save(self, root: str | Path) -> Path:
        """Write the buffer's episodes as a LeRobotDataset at ``root``.

        A buffer may mix recorders (a twin buffer and plant episodes); an optional field
        that only some of its episodes log (``observation.effort``) is left out.
        """
        if not self.episodes:
            raise LearnError("the replay buffer is empty; nothing to save")
        shared = set.intersection(*(set(e.data) for e in self.episodes))
        export_dataset(
            (
                replace(e, data={k: v for k, v in e.data.items() if k in shared})
                for e in self.episodes
            ),
            root,
        )
        return Path(root)

    # ----------------------------------------------------------------- indexing
    @property
    def num_steps(self) -> int:
        return sum(len(e) for e in self.episodes)

    def __len__(self) -> int:
        return self.num_steps

    def _build(self, gamma: float) -> None:
        if self._built_for == gamma:
            return
        columns: dict[str, list[np.ndarray]] = {
            "state": [], "env": [], "action": [], "reward": [], "terminal": [],
            "end": [], "mc": [], "intervention": [], "demo": [], "episode": [], "estimate": [],
        }  # fmt: skip
        images: dict[str, list[np.ndarray]] = {c: [] for c in self.cameras}
        self._instructions = []
        total = 0
        for index, episode in enumerate(self.episodes):
            n = len(episode)
            success = np.asarray(episode.data[SUCCESS], bool)
            reward = np.where(success, self.rewards.success, self.rewards.step)
            intervention = np.asarray(episode.data.get(INTERVENTION, np.zeros(n)), bool)
            terminal, end = success.copy(), np.full(n, n)
            if self.rewards.takeover is not None:
                takeover = np.flatnonzero(~intervention[:-1] & intervention[1:])
                reward[takeover] += self.rewards.takeover
                terminal[takeover] = True
                after = np.searchsorted(takeover, np.arange(n))  # the stretch's takeover
                inside = after < len(takeover)
                end[inside] = takeover[after[inside]] + 1
            columns["state"].append(np.asarray(episode.data[STATE], np.float32))
            if ENVIRONMENT_STATE in episode.data:
                columns["env"].append(np.asarray(episode.data[ENVIRONMENT_STATE], np.float32))
            columns["action"].append(np.asarray(episode.data[ACTION], np.float32))
            columns["reward"].append(reward.astype(np.float32))
            columns["terminal"].append(terminal)
            columns["end"].append(total + end)
            columns["mc"].append(discounted_returns(reward, gamma, terminal).astype(np.float32))
            columns["intervention"].append(intervention)
            columns["demo"].append(intervention | (episode.meta.source in DEMO_SOURCES))
            columns["episode"].append(np.full(n, index))
            for camera in self.cameras:
                images[camera].append(episode.images[camera])
            if self.estimate is not None:
                columns["estimate"].append(self._estimates_of(episode))
            self._instructions.append(episode.meta.instruction or episode.meta.task)
            total += n
        if len(columns["env"]) != len(self.episodes):
            del columns["env"]  # some episode lacks object poses: none are used
        self._arrays = {k: np.concatenate(v) for k, v in columns.items() if v}
        self._images = {c: np.concatenate(v) for c, v in images.items() if v}
        self._starts = {}
        self._built_for = gamma

    def _estimates_of(self, episode: Episode) -> np.ndarray:
        key = id(episode)
        if key not in self._estimates:
            images = {c: episode.images[c] for c in self.cameras}
            state = np.asarray(episode.data[STATE], np.float32)
            self._estimates[key] = np.asarray(self.estimate(images, state), np.float32)
        return self._estimates[key]

    def valid_starts(self, chunk: int, gamma: float = 0.99) -> np.ndarray:
        """Rows from which a chunk of ``chunk`` steps has a known outcome."""
        self._build(gamma)
        if chunk not in self._starts:
            if self.num_steps == 0:
                self._starts[chunk] = np.zeros(0, np.int64)
            else:
                rows = np.arange(self.num_steps)
                end = self._arrays["end"]
                finished = self._arrays["terminal"][end - 1]
                self._starts[chunk] = rows[(rows + chunk < end) | finished]
        return self._starts[chunk]

    def sample(
        self, size: int, rng: np.random.Generator, *, chunk: int = 1, gamma: float = 0.99
    ) -> TransitionBatch:
        """``size`` transitions drawn uniformly from the valid starts."""
        starts = self.valid_starts(chunk, gamma)
        if len(starts) == 0:
            raise LearnError("the replay buffer has no complete transition to sample yet")
        return self.transitions(starts[rng.integers(len(starts), size=size)], chunk, gamma)

    def transitions(self, rows: np.ndarray, chunk: int, gamma: float) -> TransitionBatch:
        """The chunked transitions starting at ``rows`` (see the module docstring)."""
        self._build(gamma)
        a = self._arrays
        end = a["end"][rows]
        clipped, inside = chunk_rows(rows, end, chunk)
        steps = inside.sum(1)
        powers = gamma ** np.arange(chunk)[None]
        reward = (a["reward"][clipped] * powers * inside).sum(1)
        last = rows + steps - 1
        terminal = a["terminal"][last]
        next_rows = np.minimum(rows + steps, end - 1)  # unused where terminal
        env = a.get("env")
        estimate = a.get("estimate")
        return TransitionBatch(
            state=a["state"][rows],
            environment_state=None if env is None else env[rows],
            images={c: v[rows] for c, v in self._images.items()},
            instruction=[self._instructions[i] for i in a["episode"][rows]],
            actions=a["action"][clipped],
            reward=reward.astype(np.float32),
            discount=np.where(terminal, 0.0, gamma**steps).astype(np.float32),
            next_state=a["state"][next_rows],
            next_environment_state=None if env is None else env[next_rows],
            next_images={c: v[next_rows] for c, v in self._images.items()},
            mc_return=a["mc"][rows],
            intervention=a["intervention"][rows],
            demo=a["demo"][rows],
            estimates=None if estimate is None else estimate[rows],
            next_estimates=None if estimate is None else estimate[next_rows],
        )


def discounted_returns(
    rewards: np.ndarray, gamma: float, terminal: np.ndarray | None = None
) -> np.ndarray:
    """G_t = sum_k gamma^k r_{t+k} to the episode's end, or to the next ``terminal``
    step (a takeover ends the policy's stretch)."""
    returns = np.zeros(len(rewards), np.float64)
    running = 0.0
    for t in range(len(rewards) - 1, -1, -1):
        continues = terminal is None or not terminal[t]
        running = rewards[t] + (gamma * running if continues else 0.0)
        returns[t] = running
    return returns


def concat_batches(batches: Sequence[TransitionBatch]) -> TransitionBatch:
    """One batch from several (e.g. the demo and online halves of an RLPD batch)."""

    def join(values):
        if values[0] is None:
            return None
        if isinstance(values[0], dict):
            return {k: np.concatenate([v[k] for v in values]) for k in values[0]}
        if isinstance(values[0], list):
            return [x for v in values for x in v]
        return np.concatenate(values)

    fields = TransitionBatch.__dataclass_fields__
    return TransitionBatch(**{f: join([getattr(b, f) for b in batches]) for f in fields})


@dataclass
class MixedSampler:
    """RLPD-style sampling: each batch takes ``ratios[i]`` of its rows from buffer i.

    Empty buffers give their share to the others, so learning can start from demos
    alone and mix in online data as it arrives.
    """

    buffers: list[ReplayBuffer]
    ratios: list[float]

    def __post_init__(self) -> None:
        if len(self.buffers) != len(self.ratios):
            raise LearnError("one sampling ratio per buffer is needed")
        if any(r < 0 for r in self.ratios) or sum(self.ratios) <= 0:
            raise LearnError("sampling ratios must be non-negative and not all zero")

    def sample(
        self, size: int, rng: np.random.Generator, *, chunk: int, gamma: float
    ) -> tuple[TransitionBatch, np.ndarray]:
        """A batch and, per row, the index of the buffer it came from."""
        ready = [
            (i, r)
            for i, (b, r) in enumerate(zip(self.buffers, self.ratios, strict=True))
            if r > 0 and len(b.valid_starts(chunk, gamma))
        ]
        if not ready:
            raise LearnError("no replay buffer has transitions to sample yet")
        weights = np.array([r for _, r in ready]) / sum(r for _, r in ready)
        counts = np.floor(weights * size).astype(int)
        counts[0] += size - counts.sum()
        parts = [
            (i, self.buffers[i].sample(int(n), rng, chunk=chunk, gamma=gamma))
            for (i, _), n in zip(ready, counts, strict=True)
            if n
        ]
        origin = np.concatenate([np.full(len(b), i) for i, b in parts])
        return concat_batches([b for _, b in parts]), origin
