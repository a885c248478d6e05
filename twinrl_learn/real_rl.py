"""Stage III: RL on the real robot (the plant here) with a human in the loop.

One episode at a time on the robot, each reset drawn by a :class:`ResetPlanner`:
with probability ``target_ratio`` from the current failure-mining targets (S_target,
sampled in proportion to their mining score), otherwise uniformly over the regions.
Every ``refresh_every`` episodes the targets are mined again in the twin with the
latest weights (:func:`twinrl_learn.mining.mine`). Each reset configuration is
rendered from the twin and logged to a Rerun recording, which shows an operator of a
real cell where to put the object; the plant resets programmatically.

Each episode runs the robot loop (:func:`twinrl_robot.loop.run_episode`): the actor
samples the policy's action chunks, and the robot is wrapped in an operator's takeover
(:class:`~twinrl_robot.wrappers.OperatorTakeover`: the plant's
:class:`~twinrl_robot.operator.SimulatedOperator`, a teleop device on a real cell) and,
when the policy's ``grasp_hold`` says so, the grasp hold. The operator's steps are
flagged ``intervention`` and the episode joins the demo buffer; a takeover ends the
policy's stretch for the critic (see :mod:`twinrl_learn.replay`). The replay buffer
starts as the twin buffer (D_real <- D_twin), the demo buffer as the real demos, and,
with ``keep_critic``, the critic as Stage II's.

The loop never waits for learning: each robot step grants the :class:`Learner` ``utd``
updates, which it runs in its own thread while the arm moves; between episodes the
actor takes the new weights (after the learner has caught up, with ``learner_sync``).

Plant time counts robot steps only (10 Hz: 600 steps = 1 min). Progress is measured
every ``eval_every`` robot steps by evaluating the deterministic policy on a fixed
grid of configurations in a separate plant (an evaluation session, not training
time: it does not count as interaction and its episodes never enter a buffer).

Outputs (besides :mod:`twinrl_learn.online`'s)::

    out/evaluations/<steps>/   eval.json, heatmap.png, session/ (source eval)
    out/mining/<episode>.json  the targets used from that episode on (and the evaluation)
    out/resets-<episode>.rrd   each episode's reset configuration rendered from the twin
    out/evaluations.json       [{"plant_steps", "plant_minutes", "success_rate"}, ...]
    out/curve.png              evaluation success per region against plant minutes
    out/timing.json            the control loop's period (p50 / p99 / max, s) this session
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import rerun as rr
import torch

from twinrl_data.atomic import write_text_atomic
from twinrl_data.errors import SettingError
from twinrl_data.recorder import Recorder
from twinrl_learn.agent import Agent
from twinrl_learn.errors import LearnError
from twinrl_learn.evaluate import evaluate
from twinrl_learn.learner import Learner, actor_copy
from twinrl_learn.mining import Target, load_targets, mine
from twinrl_learn.online import RUN_FILE, OnlineRun, RoundRecord
from twinrl_learn.policy import Policy
from twinrl_learn.replay import ReplayBuffer
from twinrl_learn.runners import TwinrlRunner
from twinrl_learn.settings import RealRLSettings, RLConfig
from twinrl_robot.backends import open_robot
from twinrl_robot.loop import privileged_success, run_episode
from twinrl_robot.operator import Operator, SimulatedOperator
from twinrl_robot.robot import Robot
from twinrl_robot.wrappers import (
    GraspHold,
    OperatorTakeover,
    random_states,
    restore_random_states,
)
from twinrl_sim.env import TwinEnv
from twinrl_sim.tasks import REGION_NAMES, Task, TaskConfig, make_task

EVALUATIONS_FILE = "evaluations.json"
TIMING_FILE = "timing.json"


@dataclass
class EvalPoint:
    """One evaluation of the policy during real RL."""

    plant_steps: int
    plant_minutes: float
    success_rate: dict[str, float]
    episodes: int


class ResetPlanner:
    """Next episode's configuration: a mining target (probability ``ratio``, drawn in
    proportion to score) or a uniform draw over the regions."""

    def __init__(self, task: Task, targets: list[Target], ratio: float) -> None:
        self.task, self.ratio = task, ratio
        self.targets = targets

    def next(self, rng: np.random.Generator) -> tuple[TaskConfig, str, str]:
        """``(config, region, origin)`` with origin ``target`` or ``uniform``."""
        if self.targets and rng.random() < self.ratio:
            scores = np.array([max(t.score, 1e-6) for t in self.targets])
            target = self.targets[int(rng.choice(len(self.targets), p=scores / scores.sum()))]
            return TaskConfig.from_dict(target.config), target.region, "target"
        region = REGION_NAMES[int(rng.integers(len(REGION_NAMES)))]
        return self.task.sample_config(rng, region), region, "uniform"


def _buffers(settings: RealRLSettings, policy: Policy) -> tuple[ReplayBuffer, ReplayBuffer]:
    cameras = tuple(policy.config.cameras) if policy.needs_images else ()
    rewards = settings.rl.rewards
    demo = ReplayBuffer.from_datasets(settings.demos, cameras=cameras, rewards=rewards)
    twin = [settings.twin_buffer] if settings.twin_buffer else []
    return demo, ReplayBuffer.from_datasets(twin, cameras=cameras, rewards=rewards)


class PolicySource:
    """The actor: samples the policy's action chunks (spread scaled by ``exploration``,
    drawn from its own ``generator``) and executes each open-loop; after an operator's
    step it looks afresh."""

    def __init__(self, policy: Policy, exploration: float, generator: torch.Generator) -> None:
        self.policy, self.exploration, self.generator = policy, exploration, generator
        self._instruction = ""
        self._queue: list[np.ndarray] = []

    def reset(self, task: Task, config: TaskConfig) -> None:
        self._instruction, self._queue = task.instruction, []

    def act(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        if not self._queue:
            batch = {k: np.asarray(v)[None] for k, v in observation.items()}
            chunks = self.policy.act_chunks(
                batch,
                [self._instruction],
                deterministic=False,
                std_scale=self.exploration,
                generator=self.generator,
            )
            self._queue = list(chunks[0])
        return self._queue.pop(0)

    def interrupted(self) -> None:
        self._queue = []


class RealRL:
    """A Stage III run; build with :meth:`start` or :meth:`resume`, then :meth:`run`."""

    def __init__(self, settings: RealRLSettings, run: OnlineRun, operator: Operator | None):
        self.settings, self.run_state = settings, run
        self.task = make_task(settings.task)
        self.out = Path(settings.out)
        self.operator = operator
        policy = run.agent.policy
        self.robot = self._open_robot(policy, operator)
        seed = settings.rl.seed
        self.rng = np.random.default_rng([seed, 1])  # the actor's: resets
        self.actor = actor_copy(policy)
        self.source = PolicySource(
            self.actor, run.agent.config.exploration, torch.Generator().manual_seed(seed + 1)
        )
        extra = run.extra
        if "robot_rng" in extra:
            restore_random_states(self.robot, extra["robot_rng"])
            self.rng.bit_generator.state = extra["actor_rng"]
            self.source.generator.set_state(torch.tensor(extra["actor_torch"], dtype=torch.uint8))
        if isinstance(operator, SimulatedOperator) and "operator_rng" in extra:
            operator.rng.bit_generator.state = extra["operator_rng"]
        targets = load_targets(extra["targets"]) if extra.get("targets") else []
        self.resets = ResetPlanner(self.task, targets, settings.target_ratio)
        self.evaluations = [EvalPoint(**p) for p in extra.get("evaluations", [])]
        self.periods: list[float] = []  # the control loop's, this session (s)
        self._learner: Learner | None = None
        self._render_env: TwinEnv | None = None
        self._recording: rr.RecordingStream | None = None

    def _open_robot(self, policy: Policy, operator: Operator | None) -> Robot:
        """The cell, with the operator's takeover under the policy's grasp hold."""
        s = self.settings
        cameras = tuple(policy.config.cameras) if policy.needs_images else ()
        robot = open_robot(s.robot, self.task, effects=s.effects, seed=s.rl.seed, cameras=cameras)
        if operator is not None:
            robot = OperatorTakeover(robot, operator, self.task)
        if policy.config.grasp_hold:
            robot = GraspHold(robot)
        return robot

    # ------------------------------------------------------------ lifecycle
    @classmethod
    def start(cls, settings: RealRLSettings, operator: Operator | None = None) -> RealRL:
        if not settings.init:
            raise SettingError(
                "init", "is needed to start a run: a policy checkpoint to start from"
            )
        if settings.targets:
            load_targets(settings.targets)  # fail before anything is written
        policy = Policy.from_pretrained(settings.init)
        demo, twin = _buffers(settings, policy)
        agent = Agent(policy, settings.rl)
        if settings.keep_critic and not agent.adopt_critic(settings.init):
            raise SettingError(
                "keep_critic", f"needs an RL agent as init; {settings.init} holds no agent.pt"
            )
        run = OnlineRun.start(settings.out, agent, demo, twin)
        if settings.targets:
            kept = run.out / "mining" / "initial.json"
            kept.parent.mkdir(parents=True)
            shutil.copyfile(settings.targets, kept)
            run.extra["targets"] = str(kept)
        write_text_atomic(run.out / "settings.json", json.dumps(asdict(settings), indent=1))
        return cls(settings, run, _operator(settings, operator))

    @classmethod
    def resume(cls, settings: RealRLSettings, operator: Operator | None = None) -> RealRL:
        """Continue the run in ``settings.out`` with the RL settings it started with."""
        out = Path(settings.out)
        if not (out / RUN_FILE).is_file():
            raise LearnError(f"{out / RUN_FILE} does not exist: there is no run to resume")
        policy = Policy.from_pretrained(out / "agent")
        settings.rl = RLConfig.load(out / "agent")
        demo, twin = _buffers(settings, policy)
        run = OnlineRun.resume(out, demo, twin)
        return cls(settings, run, _operator(settings, operator))

    def checkpoint(self) -> None:
        """Save everything :meth:`resume` needs (between episodes, no update running)."""
        extra = self.run_state.extra
        extra["robot_rng"] = random_states(self.robot)
        extra["actor_rng"] = self.rng.bit_generator.state
        extra["actor_torch"] = self.source.generator.get_state().tolist()
        if isinstance(self.operator, SimulatedOperator):
            extra["operator_rng"] = self.operator.rng.bit_generator.state
        extra["evaluations"] = [asdict(p) for p in self.evaluations]
        with self._learner_idle():
            self.run_state.checkpoint()

    # ------------------------------------------------------------------ run
    def run(
        self,
        *,
        on_episode: Callable[[RoundRecord, RealRL], None] | None = None,
        on_update: Callable[[int], None] | None = None,
    ) -> OnlineRun:
        """Run until ``plant_steps`` robot steps; returns the :class:`OnlineRun`."""
        run, settings = self.run_state, self.settings
        try:
            if run.agent.updates < run.agent.config.offline_steps and not run.history:
                run.pretrain(on_update)
                self.actor.load_state_dict(run.agent.policy.state_dict())
                self.checkpoint()
            self._learner = Learner(run)
            if not self.evaluations:
                self.evaluate()
                self.checkpoint()
            while run.agent.env_steps < settings.plant_steps:
                episode_index = len(run.history)
                if self._refresh_due(episode_index):
                    self.refresh_targets(episode_index)
                config, region, origin = self.resets.next(self.rng)
                self._show_reset(episode_index, config, region, origin)
                record = self.episode(config, region, origin)
                if self._evaluation_due():
                    self.evaluate()
                self.checkpoint()
                if on_episode is not None:
                    on_episode(record, self)
            if self.evaluations[-1].plant_steps != run.agent.env_steps:
                self.evaluate()
                self.checkpoint()
        finally:
            self.close()
        plot_evaluations(
            self.evaluations, self.out / "curve.png", title=f"real RL: {self.task.name}"
        )
        write_text_atomic(self.out / TIMING_FILE, json.dumps(loop_timing(self.periods), indent=1))
        return run

    def close(self) -> None:
        if self._learner is not None:
            self._learner.close()
            self._learner = None
        self.robot.close()
        if self._render_env is not None:
            self._render_env.close()
            self._render_env = None
        if self._recording is not None:
            self._recording.flush()
            self._recording.disconnect()
            self._recording = None

    # -------------------------------------------------------------- episodes
    def episode(self, config: TaskConfig, region: str, origin: str) -> RoundRecord:
        """One robot episode from ``config`` (the robot loop, logged as ``real_rl``); the
        learner updates meanwhile; then the episode joins the buffers and the actor takes
        the new weights."""
        run, learner = self.run_state, self._learner
        if learner is None:
            raise RuntimeError("RealRL.episode runs inside RealRL.run, which starts the learner")
        meta = self.task.episode_meta(
            source="real_rl",
            world=self.robot.world,
            names=self.robot.names,
            config=config,
            region=region,
            policy=f"rl:{run.agent.config.method}",
            operator="simulated" if isinstance(self.operator, SimulatedOperator) else None,
        )
        outcome = run_episode(
            self.robot,
            self.source,
            self.task,
            config,
            judge=privileged_success(self.robot),
            recorder=Recorder(run.session),
            meta=meta,
            on_step=lambda _t, _sent: learner.grant(1),
        )
        self.periods.extend(outcome.periods)
        if self.settings.learner_sync:
            learner.wait()
        assert outcome.path is not None
        episodes = learner.add_episodes([outcome.path])
        self.actor.load_state_dict(learner.weights())
        run.extra.setdefault("reset_origins", []).append(origin)
        return run.record_round(episodes, learner.metrics)

    def _refresh_due(self, episode_index: int) -> bool:
        every = self.settings.refresh_every
        if self.settings.targets is None or every == 0:
            return False
        return episode_index > 0 and episode_index % every == 0

    def refresh_targets(self, episode_index: int) -> None:
        """Mine S_target again in the twin with the current weights."""
        s = self.settings
        path = self.out / "mining" / f"{episode_index:05d}.json"
        if path.exists():  # an interrupted refresh: mine afresh
            path.unlink()
            shutil.rmtree(path.with_suffix(""), ignore_errors=True)
        runner = TwinrlRunner(self.actor, name=f"rl@{episode_index}")
        with self._learner_idle():
            mine(
                runner,
                s.task,
                out=path,
                grid=s.mining_grid,
                episodes=s.mining_episodes,
                tau=s.tau,
                k=s.k,
                seed=s.rl.seed + episode_index,
            )
        self.resets.targets = load_targets(path)
        self.run_state.extra["targets"] = str(path)

    @contextmanager
    def _learner_idle(self) -> Iterator[None]:
        """No update runs meanwhile: a checkpoint saves the networks, and evaluation and
        mining re-seed torch's global stream, which the learner's updates draw from."""
        if self._learner is None:
            yield
            return
        with self._learner.paused():
            yield

    def _evaluation_due(self) -> bool:
        every = self.settings.eval_every
        last = self.evaluations[-1].plant_steps if self.evaluations else 0
        return every > 0 and self.run_state.agent.env_steps - last >= every

    def evaluate(self) -> EvalPoint:
        """Evaluate the deterministic policy on the fixed grid in a separate plant."""
        s, steps = self.settings, self.run_state.agent.env_steps
        folder = self.out / "evaluations" / f"{steps:06d}"
        shutil.rmtree(folder, ignore_errors=True)  # an interrupted evaluation
        runner = TwinrlRunner(self.actor, name=f"rl@{steps}")
        with self._learner_idle():
            report = evaluate(
                runner,
                s.task,
                world="plant",
                effects=s.effects,
                grid=s.eval_grid,
                episodes=s.eval_episodes,
                seed=10_000 + s.rl.seed,
                out=folder,
            )
        point = EvalPoint(
            plant_steps=steps,
            plant_minutes=steps / self.robot.control_hz / 60,
            success_rate=report.success_rate(),
            episodes=report.episodes,
        )
        self.evaluations.append(point)
        evaluations = [asdict(p) for p in self.evaluations]
        write_text_atomic(self.out / EVALUATIONS_FILE, json.dumps(evaluations, indent=1))
        return point

    def _show_reset(self, index: int, config: TaskConfig, region: str, origin: str) -> None:
        """Render the reset configuration from the twin into the run's Rerun recording
        (on a real cell the operator places the object to match it)."""
        if not self.settings.show_resets:
            return
        if self._render_env is None:
            self._render_env = TwinEnv(self.task, cameras=("front",))
            self._recording = rr.RecordingStream("twinrl_resets")
            self._recording.save(str(self.out / f"resets-{index:05d}.rrd"))
        obs, _ = self._render_env.reset(options={"config": config})
        rec = self._recording
        rec.set_time("episode", sequence=index)
        rec.log("reset/front", rr.Image(obs["observation.images.front"]))
        target = np.asarray(config.target[:2])
        rec.log(
            "reset/config",
            rr.TextLog(f"episode {index}: {origin} reset in {region}, target at {target.round(3)}"),
        )


def _operator(settings: RealRLSettings, operator: Operator | None) -> Operator | None:
    if operator is not None or settings.operator is None:
        return operator
    return SimulatedOperator(settings.operator, seed=settings.rl.seed + 7)


def loop_timing(periods: list[float]) -> dict[str, float | int]:
    """The control loop's period (s) over ``periods``: median, 99th percentile, worst."""
    if not periods:
        return {"steps": 0}
    values = np.asarray(periods)
    return {
        "steps": len(values),
        "p50_s": float(np.percentile(values, 50)),
        "p99_s": float(np.percentile(values, 99)),
        "max_s": float(values.max()),
    }


def minutes_to(evaluations: list[EvalPoint], region: str, level: float = 0.95) -> float | None:
    """Plant minutes at the first evaluation with ``region`` success >= ``level``."""
    for point in evaluations:
        if point.success_rate.get(region, 0.0) >= level:
            return point.plant_minutes
    return None


def load_evaluations(folder: str | Path) -> list[EvalPoint]:
    path = Path(folder) / EVALUATIONS_FILE
    if not path.is_file():
        raise LearnError(f"{folder} holds no {EVALUATIONS_FILE}; it is not a real-RL run")
    return [EvalPoint(**p) for p in json.loads(path.read_text())]


def plot_evaluations(evaluations: list[EvalPoint], path: Path, *, title: str = "") -> None:
    """Evaluation success per region against plant minutes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6), dpi=120)
    for region in REGION_NAMES:
        xs = [p.plant_minutes for p in evaluations if region in p.success_rate]
        ys = [p.success_rate[region] for p in evaluations if region in p.success_rate]
        ax.plot(xs, ys, marker="o", ms=3, lw=1.6, label=region)
    ax.axhline(0.95, color="grey", lw=0.8, ls="--")
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("plant minutes (10 Hz robot steps)")
    ax.set_ylabel("evaluation success")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
