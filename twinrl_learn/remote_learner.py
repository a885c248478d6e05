"""Real RL's learner in another process or on another machine: the actor–learner split.

The actor (the robot loop, the person at the controls, the recording) stays beside the
robot; the learner (the replay buffers and the gradient updates) runs as one actor
object (:mod:`twinrl_data.actors`) in a spawned process here, or as a Ray actor on a
cluster's node, e.g. one with a GPU. After each episode the actor sends it, the MCAP
file's bytes as recorded, with the robot steps it bought, and takes the weights back:
one round trip per episode, none inside the robot loop. With ``sync`` the learner runs
every update the episode bought before it answers (the run takes ``utd`` updates per
robot step, as in one process); without, it answers at once and runs them meanwhile.

The learner keeps a run folder of its own (an :class:`~twinrl_learn.online.OnlineRun`
whose session holds the episodes it was sent) and checkpoints after each, so a learner
that is killed starts again from its folder holding every episode it acknowledged. The
actor's session keeps every episode whatever happens. While the learner is gone the
actor acts with the last weights it got and says so; at the end of each later episode
it starts a learner again, which is sent the episodes it lacks, in order, before the
run goes on; a learner that fails to start (its folder unreadable, the cluster gone) is
said and tried again after the next episode. A learner whose folder is gone starts from
the actor's last weights with a new critic. One learner at a time holds a folder:
another pointed at it is refused. The learner alone holds the buffers: it reads the
demos and the twin buffer as its machine sees those paths, and the actor, started or
resumed, reads neither them nor its episodes back (they stay in its session).
"""

from __future__ import annotations

import os
import shutil
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import torch

from twinrl_data.actors import ActorLost, Actors, ProcessActors
from twinrl_data.errors import DataError
from twinrl_data.executor import LOCAL, cluster_address
from twinrl_data.locking import FolderLock
from twinrl_data.mcap_log import read_episode, read_meta, read_summary
from twinrl_data.schema import Episode
from twinrl_learn.agent import Agent
from twinrl_learn.compute import resolve_device
from twinrl_learn.errors import LearnError
from twinrl_learn.learner import Learner
from twinrl_learn.online import RUN_FILE, OnlineRun
from twinrl_learn.policy import Policy
from twinrl_learn.replay import ReplayBuffer
from twinrl_learn.settings import RLConfig

PROCESS = "process"  # RealRLSettings.learner: a spawned process on this machine
PREPAID = "prepaid_steps"  # run.extra: steps of re-sent episodes already counted
BEHIND_STEPS = 600  # robot steps of updates owed before the actor says the learner lags


class LearnerWarning(UserWarning):
    """The learner is lost or behind; the actor goes on with the weights it has."""


@dataclass(frozen=True)
class LearnerSpec:
    """What a learner needs to start, or to start again from its folder."""

    folder: str  # its own run folder, on its machine
    init: str  # the policy checkpoint the run starts from
    rl: RLConfig
    # (env steps, updates) of a run that has begun: a learner without its folder starts
    # from the actor's last weights there, with a new critic and no second offline phase
    counters: tuple[int, int] | None = None
    demos: list[str] = field(default_factory=list)
    twin_buffer: str | None = None
    keep_critic: bool = False
    device: str = "auto"


@dataclass
class LearnerReply:
    """The learner's state after a call: the weights to act with and how far it is."""

    weights: dict[str, torch.Tensor]
    updates: int
    behind: float  # updates bought and not yet run
    metrics: dict[str, float]
    held: list[str]  # names of the episodes it holds, in order


def learning_buffers(
    demos: list[str], twin_buffer: str | None, rl: RLConfig, policy: Policy
) -> tuple[ReplayBuffer, ReplayBuffer]:
    """The demo buffer (real demos) and the online buffer's start (Stage II's twin
    buffer, or empty) that ``policy`` learns from."""
    views = policy.replay_views()
    demo = ReplayBuffer.from_datasets(demos, rewards=rl.rewards, **views)
    twin = [twin_buffer] if twin_buffer else []
    return demo, ReplayBuffer.from_datasets(twin, rewards=rl.rewards, **views)


class LearnerService:
    """The learner's side (in its own process); see the module docstring."""

    def __init__(self, spec: LearnerSpec) -> None:
        folder, device = Path(spec.folder), resolve_device(spec.device)
        self._lock = hold_learner_folder(folder)
        try:
            self._open(spec, folder, device)
        except BaseException:
            self._lock.release()
            raise

    def _open(self, spec: LearnerSpec, folder: Path, device: torch.device) -> None:
        if folder.exists() and not (folder / RUN_FILE).is_file():
            shutil.rmtree(folder)  # stopped before its first checkpoint: nothing acknowledged
        if (folder / RUN_FILE).is_file():  # a learner that stopped: from its checkpoint
            policy = Policy.from_pretrained(folder / "agent", device)
            rl = RLConfig.load(folder / "agent")
            demo, twin = learning_buffers(spec.demos, spec.twin_buffer, rl, policy)
            run = OnlineRun.resume(folder, demo, twin, device)
        else:
            policy = Policy.from_pretrained(spec.init, device)
            demo, twin = learning_buffers(spec.demos, spec.twin_buffer, spec.rl, policy)
            agent = Agent(policy, spec.rl)
            if spec.counters is not None:  # the actor's run goes on: no offline phase again
                agent.env_steps, agent.updates = spec.counters
            elif spec.keep_critic and not agent.adopt_critic(spec.init):
                raise LearnError(f"keep_critic needs an RL agent as init; {spec.init} has none")
            run = OnlineRun.start(folder, agent, demo, twin)
            # The episodes it is sent again bought their updates from the learner before.
            run.extra[PREPAID] = spec.counters[0] if spec.counters is not None else 0
            run.pretrain()
            run.checkpoint()
        self.run = run
        self.learner = Learner(run)

    def pid(self) -> int:
        return os.getpid()

    def status(self) -> LearnerReply:
        with self.learner.paused() as run:
            return LearnerReply(
                weights={
                    k: v.detach().cpu().clone() for k, v in run.agent.policy.state_dict().items()
                },
                updates=run.agent.updates,
                behind=run.pending_updates,
                metrics=dict(self.learner.metrics),
                held=[p.name for p in run.session.episode_paths()],
            )

    def episode(self, name: str, data: bytes, steps: int, sync: bool) -> LearnerReply:
        """Take one episode the actor recorded (``steps`` robot steps), then answer."""
        with self.learner.paused() as run:
            owed = run.extra.get(PREPAID, 0)
            prepaid = min(owed, steps)
            run.extra[PREPAID] = owed - prepaid
        if steps > prepaid:
            self.learner.grant(steps - prepaid)
        if sync:
            self.learner.wait()
        with self.learner.paused() as run:
            path = run.session.path / "episodes" / name
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
            run.session.register(path, read_meta(path), steps)
            run.add_episodes([path])
            run.checkpoint()
        return self.status()

    def close(self) -> None:
        self.learner.close()
        self._lock.release()


def hold_learner_folder(folder: Path) -> FolderLock:
    """Hold the lock that keeps a second learner out of ``folder`` while this one lives
    (a second run given the same folder, or a learner started again while the one it
    replaces still runs): two would write one run's checkpoints over each other. The
    lock file lies beside the folder, which a run starts empty; the kernel frees it when
    its process dies."""
    folder.parent.mkdir(parents=True, exist_ok=True)
    lock = FolderLock(
        folder.parent,
        wait=0.0,
        file=f".{folder.name}.lock",
        what=f"the learner folder {folder}",
    )
    try:
        return lock.acquire()
    except DataError as err:
        raise LearnError(str(err)) from None


def _episode_steps(path: Path) -> int:
    length = read_summary(path).length
    if length is None:
        raise LearnError(f"{path} is not a finished episode; it cannot be learnt from")
    return length


class RemoteLearner:
    """The actor's side, with :class:`~twinrl_learn.learner.Learner`'s interface: the
    actor's own ``run`` keeps the session, counters and history; ``where`` is
    :data:`PROCESS` or a Ray cluster as ``cluster`` settings take it."""

    def __init__(
        self,
        run: OnlineRun,
        spec: LearnerSpec,
        where: str,
        *,
        sync: bool = True,
        timeout_s: float | None = None,
        say: Callable[[str], None] | None = None,
    ) -> None:
        self.run, self.spec, self.where, self.sync = run, spec, where, sync
        self.timeout_s = timeout_s  # an episode's answer, a start again (not the first's)
        self.say = say or (lambda message: warnings.warn(message, LearnerWarning, stacklevel=3))
        self.metrics: dict[str, float] = {}
        self._actors: Actors | None = None
        self._closers: list[Callable[[], None]] = []
        self._held: set[str] = set()
        self._weights: dict[str, torch.Tensor] | None = None
        try:
            self._connect()  # the first learner must start: there is nothing to act with else
        except BaseException:
            self.close()
            raise
        ours = {p.name for p in run.session.episode_paths()}
        extra = len(self._held - ours)
        if extra:  # the actor stopped between the learner's checkpoint and its own
            self.say(
                f"the learner learnt from {extra} episode(s) this run no longer holds (the "
                "actor stopped before saving them; they are in its session's discarded/)"
            )
        self._deliver()  # a resumed actor's episodes the learner lacks

    # ------------------------------------------------------------------ actor side
    def grant(self, env_steps: int) -> None:
        """Count the actor's steps (the updates they buy are the learner's); they are sent
        with the episode at its end."""
        self.run.agent.env_steps += env_steps

    def wait(self, timeout_s: float | None = None) -> bool:
        """The episode's round trip waits (with ``sync``); nothing to wait for here."""
        return True

    @contextmanager
    def paused(self) -> Iterator[OnlineRun]:
        """No update runs in this process; the actor's run as it is."""
        yield self.run

    def add_episodes(self, paths: list[Path]) -> list[Episode]:
        """Send the learner every episode it lacks (these and any it missed), read
        ``paths`` back for the actor's history."""
        self._deliver()
        return [read_episode(path, images=False) for path in paths]

    def weights(self) -> dict[str, torch.Tensor]:
        """The last weights the learner sent."""
        assert self._weights is not None
        return self._weights

    def learner_pid(self) -> int:
        """The learner process's id (on its machine)."""
        assert self._actors is not None, "no learner is connected"
        return self._actors.call("pid", [()])[0]

    def close(self) -> None:
        if self._actors is not None:  # a lost worker is cleaned up without a word
            self._actors.close()
        for close in self._closers:
            close()
        self._actors, self._closers = None, []

    # ---------------------------------------------------------------- the learner
    def _connect(self, timeout_s: float | None = None) -> None:
        """Start a learner; ``timeout_s`` limits its start (none for the first, which may
        run the offline phase)."""
        if self.where == PROCESS:
            self._actors = ProcessActors(LearnerService, [{"spec": self.spec}], timeout_s)
        else:
            from twinrl_data.ray_executor import RayExecutor

            address = cluster_address(self.where)
            executor = RayExecutor(1, address=None if address == LOCAL else address)
            self._closers.append(executor.close)
            # Ray shows an actor only the GPUs it reserves: one for a learner on cuda, or
            # on auto where the cluster has one.
            device = self.spec.device
            gpus = 1 if device.startswith("cuda") or (device == "auto" and executor.gpus()) else 0
            self._actors = executor.actors(LearnerService, [{"spec": self.spec}], gpus=gpus)
        self._adopt(self._actors.call("status", [()], timeout_s)[0])  # Ray: after its start

    def _deliver(self) -> None:
        """Send the episodes the learner lacks, oldest first; on the learner's loss, go
        on with the weights there are, and start a learner again next time."""
        try:
            if self._actors is None and not self._start_again():
                return
            for path in self.run.session.episode_paths():
                if path.name not in self._held:
                    reply = self._actors.call(  # type: ignore[union-attr]
                        "episode",
                        [(path.name, path.read_bytes(), _episode_steps(path), self.sync)],
                        self.timeout_s,
                    )[0]
                    self._adopt(reply)
        except ActorLost as err:
            self.say(f"the learner is lost ({err}); {self._going_on()}")
            self.close()

    def _start_again(self) -> bool:
        """Start a learner in place of a lost one. One that fails to start, for whatever
        reason (its folder unreadable, the cluster gone, no memory, no answer within the
        learner's time limit), is said and tried again after the next episode: the robot
        session never stops for the learner."""
        try:
            self._connect(self.timeout_s)  # a learner slow to start again is a lost one
        except Exception as err:  # any failure: the robot goes on
            self.close()
            self.say(
                f"a learner could not start again ({type(err).__name__}: {err}); "
                f"{self._going_on()}; trying again after the next episode"
            )
            return False
        self.say(
            f"a learner is back at update {self.run.agent.updates}; sending it the "
            "episodes it lacks"
        )
        return True

    def _going_on(self) -> str:
        waiting = sum(p.name not in self._held for p in self.run.session.episode_paths())
        return (
            f"acting with the weights of update {self.run.agent.updates}, "
            f"{waiting} episode(s) kept for it"
        )

    def _adopt(self, reply: LearnerReply) -> None:
        self._weights, self._held = reply.weights, set(reply.held)
        self.metrics = reply.metrics
        self.run.agent.updates = reply.updates
        self.run.agent.policy.load_state_dict(reply.weights)  # what the actor checkpoints
        behind = reply.behind
        if not self.sync and behind > BEHIND_STEPS * self.run.agent.config.utd:
            self.say(f"the learner is {behind:.0f} updates behind the robot")
