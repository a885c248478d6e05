"""Online RL bookkeeping shared by twin RL (Stage II) and real/plant RL (Stage III).

An :class:`OnlineRun` owns the agent, the demo buffer (demos + interventions) and the
online buffer, the session every rollout is logged to, the sampling RNG and the
learning history. Rollouts happen in *rounds* (one episode per environment); a round's
episodes are read back from the log into the online buffer (the buffer is a view over
the logged episodes), and checkpoints are taken between rounds, so ``resume`` continues
exactly: same buffers, networks, optimizers, counters and random streams.

Folder layout::

    out/session/        every rollout as an episode
    out/agent/          the latest policy (Policy.from_pretrained) + agent.pt
    out/run.json        counters, RNG state and history (what resume reads)
    out/curve.png       success per region against environment steps
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from twinrl_data.mcap_log import read_episode
from twinrl_data.schema import Episode
from twinrl_data.session import Session
from twinrl_learn.agent import Agent
from twinrl_learn.errors import LearnError
from twinrl_learn.replay import MixedSampler, ReplayBuffer

RUN_FILE = "run.json"


@dataclass
class RoundRecord:
    """What one round of rollouts did (one row of the learning history)."""

    env_steps: int
    updates: int
    episodes: int
    successes: dict[str, list[int]]  # region -> [successes, episodes]
    interventions: int = 0
    metrics: dict[str, float] = field(default_factory=dict)


class OnlineRun:
    """See the module docstring. Create with :meth:`start` or :meth:`resume`."""

    def __init__(
        self,
        out: Path,
        agent: Agent,
        demo: ReplayBuffer,
        online: ReplayBuffer,
        session: Session,
        rng: np.random.Generator,
        history: list[RoundRecord],
    ) -> None:
        self.out, self.agent, self.demo, self.online = out, agent, demo, online
        self.session, self.rng, self.history = session, rng, history
        ratio = agent.config.demo_ratio
        self.sampler = MixedSampler([demo, online], [ratio, 1.0 - ratio])
        self._pending_updates = 0.0
        self.extra: dict = {}  # a caller's own resumable state (JSON), saved in run.json

    # ------------------------------------------------------------ lifecycle
    @classmethod
    def start(
        cls, out: str | Path, agent: Agent, demo: ReplayBuffer, online: ReplayBuffer | None = None
    ) -> OnlineRun:
        """A new run; ``online`` pre-fills the online buffer (Stage III's D_real <- D_twin)."""
        out = Path(out)
        if out.exists() and any(out.iterdir()):
            raise LearnError(f"{out} already holds a run; resume it or choose another folder")
        session = Session.create(out / "session")
        if online is None:
            online = ReplayBuffer(
                cameras=demo.cameras, estimate=demo.estimate, rewards=agent.config.rewards
            )
        rng = np.random.default_rng(agent.config.seed)
        return cls(out, agent, demo, online, session, rng, [])

    @classmethod
    def resume(
        cls,
        out: str | Path,
        demo: ReplayBuffer,
        online: ReplayBuffer | None = None,
        device: str | torch.device = "cpu",
        *,
        fill: bool = True,
    ) -> OnlineRun:
        """Continue the run in ``out`` from its last checkpoint (between two rounds), its
        agent on ``device``; ``online`` is the same pre-filled buffer the run started
        with, if any. ``fill`` reads the run's episodes back into the buffers (not for an
        actor whose learner runs apart and holds them)."""
        out = Path(out)
        if not (out / RUN_FILE).is_file():
            raise LearnError(f"{out / RUN_FILE} does not exist: there is no run to resume")
        state = json.loads((out / RUN_FILE).read_text())
        agent = Agent.load(out / "agent", device)
        session = Session(out / "session")
        kept = state["episodes_logged"]
        session.truncate(kept)  # episodes of a round the interruption cut short
        if online is None:
            online = ReplayBuffer(
                cameras=demo.cameras, estimate=demo.estimate, rewards=agent.config.rewards
            )
        rng = np.random.default_rng()
        rng.bit_generator.state = state["rng"]
        history = [RoundRecord(**r) for r in state["history"]]
        run = cls(out, agent, demo, online, session, rng, history)
        if fill:
            run.add_episodes(session.episode_paths())
        run._pending_updates = state["pending_updates"]
        run.extra = state.get("extra", {})
        return run

    def checkpoint(self) -> None:
        """Save everything :meth:`resume` needs (call between rounds)."""
        self.agent.save(self.out / "agent")
        state = {
            "episodes_logged": len(self.session.entries),
            "rng": self.rng.bit_generator.state,
            "pending_updates": self._pending_updates,
            "history": [r.__dict__ for r in self.history],
            "extra": self.extra,
        }
        tmp = self.out / f".{RUN_FILE}"
        tmp.write_text(json.dumps(state, indent=1))
        tmp.replace(self.out / RUN_FILE)

    # -------------------------------------------------------------- learning
    def learn(self, env_steps: int) -> dict[str, float]:
        """Count ``env_steps`` new environment steps and run the updates they buy
        (``utd`` per step) here and now; returns the last update's metrics. (Real RL runs
        them apart from the robot loop instead: :mod:`twinrl_learn.learner`.)"""
        self.count_steps(env_steps)
        metrics: dict[str, float] = {}
        while self.updates_due():
            metrics = self.update_due()
        return metrics

    def count_steps(self, env_steps: int) -> None:
        """Count new environment steps; each buys ``utd`` updates."""
        self.agent.env_steps += env_steps
        self._pending_updates += self.agent.config.utd * env_steps

    @property
    def pending_updates(self) -> float:
        """Updates the counted steps bought and not yet run."""
        return self._pending_updates

    def updates_due(self) -> bool:
        """Whether the steps counted so far have bought an update not yet run."""
        return self._pending_updates >= 1

    def update_due(self) -> dict[str, float]:
        """Run one update that the counted steps bought."""
        metrics = self.update()
        self.update_done()
        return metrics

    def update_done(self) -> None:
        """Count one bought update as run."""
        self._pending_updates -= 1

    def update(self) -> dict[str, float]:
        """One gradient update on an RLPD batch."""
        agent = self.agent
        chunk, gamma = agent.policy.config.chunk, agent.config.gamma
        batch, _ = self.sampler.sample(agent.config.batch_size, self.rng, chunk=chunk, gamma=gamma)
        return agent.update(batch)

    def pretrain(self, progress: Callable[[int], None] | None = None) -> None:
        """The offline phase: ``offline_steps`` updates on the demo buffer (Cal-QL + BC)."""
        while self.agent.updates < self.agent.config.offline_steps:
            self.update()
            if progress is not None:
                progress(self.agent.updates)

    def add_episodes(self, paths: list[Path]) -> list[Episode]:
        """Read a round's logged episodes back into the buffers: episodes with human
        interventions into the demo buffer (as HiL-SERL and ConRFT do), others online."""
        episodes = []
        for path in paths:
            episode = read_episode(path, images=bool(self.demo.cameras))
            (self.demo if _has_interventions(episode) else self.online).add(episode)
            episodes.append(episode)
        return episodes

    def record_round(self, episodes: list[Episode], metrics: dict[str, float]) -> RoundRecord:
        successes: dict[str, list[int]] = {}
        for episode in episodes:
            counts = successes.setdefault(episode.meta.region or "all", [0, 0])
            counts[0] += int(bool(episode.meta.success))
            counts[1] += 1
        record = RoundRecord(
            env_steps=self.agent.env_steps,
            updates=self.agent.updates,
            episodes=len(episodes),
            successes=successes,
            interventions=sum(e.meta.num_interventions for e in episodes),
            metrics={k: float(v) for k, v in metrics.items()},
        )
        self.history.append(record)
        return record

    def success_rates(self, last_episodes: int) -> dict[str, float]:
        """Success per region over (about) the last ``last_episodes`` episodes."""
        taken, seen = [], 0
        for record in reversed(self.history):
            taken.append(record)
            seen += record.episodes
            if seen >= last_episodes:
                break
        return region_success(taken)


def region_counts(records: Iterable[RoundRecord]) -> dict[str, tuple[int, int]]:
    """(successes, episodes) per region over the episodes of ``records``."""
    totals: dict[str, tuple[int, int]] = {}
    for record in records:
        for region, (wins, count) in record.successes.items():
            before = totals.get(region, (0, 0))
            totals[region] = (before[0] + wins, before[1] + count)
    return totals


def region_success(records: Iterable[RoundRecord]) -> dict[str, float]:
    """Success per region over the episodes of ``records``."""
    return {r: wins / count for r, (wins, count) in region_counts(records).items() if count}


def _has_interventions(episode: Episode) -> bool:
    flags = episode.data.get("intervention")
    return flags is not None and bool(np.asarray(flags).any())


def plot_curve(
    history: list[RoundRecord], path: Path, *, window: int = 20, title: str = ""
) -> None:
    """Success rate per region (running over ``window`` episodes) against environment steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6), dpi=120)
    regions = sorted({r for record in history for r in record.successes})
    for region in regions:
        xs, ys, outcomes = [], [], []
        for record in history:
            wins, count = record.successes.get(region, [0, 0])
            outcomes += [1] * wins + [0] * (count - wins)
            if count:
                xs.append(record.env_steps)
                ys.append(float(np.mean(outcomes[-window:])))
        ax.plot(xs, ys, label=region, lw=1.6)
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("environment steps")
    ax.set_ylabel(f"success (last {window} episodes)")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    if regions:
        ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
