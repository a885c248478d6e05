"""Stage III: RL on the robot (the plant, or a UR cell) with a human in the loop.

One episode at a time on the robot, each reset drawn by a :class:`ResetPlanner`:
with probability ``target_ratio`` from the current failure-mining targets (S_target,
sampled in proportion to their mining score), otherwise uniformly over the regions.
Every ``refresh_every`` episodes the targets are mined again in the twin with the
latest weights (:func:`twinrl_learn.mining.mine`). Each reset configuration is
rendered from the twin and logged to a Rerun recording, which shows an operator of a
real cell where to put the object (they press Enter once it is set up); the plant and
the emulator reset programmatically.

Each episode runs the robot loop (:func:`twinrl_robot.loop.run_episode`): the actor
samples the policy's action chunks, and the robot is wrapped in an operator's takeover
(:class:`~twinrl_robot.wrappers.OperatorTakeover`: the plant's
:class:`~twinrl_robot.operator.SimulatedOperator`, or a person's teleop device through
:class:`~twinrl_robot.person_in_loop.PersonInLoop`) and,
when the policy's ``grasp_hold`` says so, the grasp hold. The operator's steps are
flagged ``intervention`` and the episode joins the demo buffer; a takeover ends the
policy's stretch for the critic (see :mod:`twinrl_learn.replay`). The replay buffer
starts as the twin buffer (D_real <- D_twin), the demo buffer as the real demos, and,
with ``keep_critic``, the critic as Stage II's. An episode's success is judged by the
cell's ground truth (plant, emulator), the person's key, or a reward classifier
(:mod:`twinrl_learn.reward_classifier`); the person's ``q`` pauses the run after the
episode, and :meth:`RealRL.resume` goes on.

The loop never waits for learning: each robot step grants the :class:`Learner` ``utd``
updates, which it runs in its own thread while the arm moves; between episodes the
actor takes the new weights (after the learner has caught up, with ``learner_sync``).

Plant time counts robot steps only (10 Hz: 600 steps = 1 min). Progress is measured
every ``eval_every`` robot steps by evaluating the deterministic policy on a fixed
grid of configurations in a separate plant (an evaluation session, not training
time: it does not count as interaction and its episodes never enter a buffer); on a UR
cell, by the success of the run's own episodes since the last point.

Outputs (besides :mod:`twinrl_learn.online`'s)::

    out/evaluations/<steps>/   eval.json, heatmap.png, session/ (source eval)
    out/mining/<episode>.json  the targets used from that episode on (and the evaluation)
    out/live-<episode>.rrd     the live view from that episode on (unless ``view`` names
                               another place): each reset rendered from the cell's twin,
                               its outlines over the live cameras, then the cameras,
                               joints and actions as they run
    out/evaluations.json       [{"plant_steps", "plant_minutes", "success_rate"}, ...]
    out/curve.png              evaluation success per region against plant minutes
    out/timing.json            the control loop's period (p50 / p99 / max, s) this session
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from twinrl_data.atomic import write_text_atomic
from twinrl_data.errors import SettingError
from twinrl_data.recorder import Recorder
from twinrl_data.schema import ENVIRONMENT_STATE, STATE
from twinrl_learn.agent import Agent
from twinrl_learn.compute import resolve_device
from twinrl_learn.errors import LearnError
from twinrl_learn.evaluate import evaluate
from twinrl_learn.learner import Learner, actor_copy
from twinrl_learn.mining import Target, load_targets, mine
from twinrl_learn.online import RUN_FILE, OnlineRun, RoundRecord, region_counts
from twinrl_learn.perception.estimator import PoseEstimator
from twinrl_learn.policy import Policy
from twinrl_learn.real_rl_progress import (
    EVALUATIONS_FILE,
    EvalPoint,
    loop_timing,
    plot_evaluations,
)
from twinrl_learn.remote_learner import LearnerSpec, RemoteLearner, learning_buffers
from twinrl_learn.replay import ReplayBuffer
from twinrl_learn.reward_classifier import RewardClassifier
from twinrl_learn.runners import TwinrlRunner
from twinrl_learn.seeing_operator import SeeingOperator
from twinrl_learn.settings import RealRLSettings, RLConfig
from twinrl_robot.backends import ROBOTS, open_robot
from twinrl_robot.cell_file import load_cell
from twinrl_robot.live_view import LiveView
from twinrl_robot.loop import Judge, privileged_success, run_episode
from twinrl_robot.operator import Operator, SimulatedOperator
from twinrl_robot.person_in_loop import PersonInLoop, RunPaused
from twinrl_robot.robot import Robot, Sent
from twinrl_robot.teleop import TerminalKeys, open_teleop
from twinrl_robot.wrappers import (
    GraspHold,
    OperatorTakeover,
    random_states,
    restore_random_states,
)
from twinrl_sim.tasks import REGION_NAMES, Task, TaskConfig, make_task, task_class, task_on_twin

TIMING_FILE = "timing.json"


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
    """The demo and online buffers the run learns from; empty where the learner runs
    apart, which reads the demos and the twin buffer itself, as its machine sees them."""
    if settings.learner:
        return learning_buffers([], None, settings.rl, policy)
    return learning_buffers(settings.demos, settings.twin_buffer, settings.rl, policy)


def learner_spec(settings: RealRLSettings, run: OnlineRun) -> LearnerSpec:
    """What a learner apart from the actor starts (or starts again) from: a run that has
    begun gives the weights and counters the actor has (a learner whose folder is gone
    starts again from them; one with its folder resumes from its own)."""
    out, begun = Path(settings.out), bool(run.history)
    return LearnerSpec(
        folder=settings.learner_folder or str(out / "learner"),
        init=str(out / "agent") if begun else settings.init,
        counters=(run.agent.env_steps, run.agent.updates) if begun else None,
        rl=settings.rl,
        demos=list(settings.demos),
        twin_buffer=settings.twin_buffer,
        keep_critic=settings.keep_critic,
        device=settings.device,
    )


class PolicySource:
    """The actor: samples the policy's action chunks (spread scaled by ``exploration``,
    drawn from its own ``generator``) and executes each open-loop; after an operator's
    step it looks afresh."""

    def __init__(self, policy: Policy, exploration: float, generator: torch.Generator) -> None:
        self.policy, self.exploration, self.generator = policy, exploration, generator
        self._instruction = ""
        self._queue: list[np.ndarray] = []
        self.observation: dict[str, np.ndarray] | None = None  # the last one acted on

    def reset(self, task: Task, config: TaskConfig) -> None:
        self._instruction, self._queue = task.instruction, []

    def act(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        self.observation = observation
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

    def __init__(
        self,
        settings: RealRLSettings,
        run: OnlineRun,
        operator: Operator | None,
        terminal: TerminalKeys | None = None,
        on_wait: Callable[[str], None] | None = None,
        classifier: RewardClassifier | None = None,
        on_notice: Callable[[str], None] | None = None,
    ):
        self.settings, self.run_state = settings, run
        self.cell = load_cell(settings.cell) if settings.cell is not None else None
        twin = None if self.cell is None else task_on_twin(settings.task, self.cell.twin)
        self.task = make_task(settings.task, twin)
        self.out = Path(settings.out)
        self.classifier = classifier
        policy = run.agent.policy
        self.person: PersonInLoop | None = None
        self._say = on_notice
        self.robot = self._open_robot(policy, operator, terminal, on_wait)
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
        self._learner: Learner | RemoteLearner | None = None
        self.view: LiveView | None = None
        if settings.show_resets:
            self.view = LiveView(
                # a file per session: a resumed run keeps the earlier sessions' views
                settings.view or str(self.out / f"live-{len(run.history):05d}.rrd"),
                self.task,
                self._cameras,
                self.robot.names.get(STATE, []),
                name="twinrl real-rl",
                environment_names=self.robot.names.get(ENVIRONMENT_STATE, []),
            )

    def _open_robot(
        self,
        policy: Policy,
        operator: Operator | None,
        terminal: TerminalKeys | None,
        on_wait: Callable[[str], None] | None,
    ) -> Robot:
        """The cell, with the operator's takeover (the person's device, or the simulated
        operator) under the policy's grasp hold."""
        s = self.settings
        cameras = list(policy.config.cameras) if policy.needs_images else []
        if self.classifier is not None:
            cameras += [c for c in self.classifier.settings.cameras if c not in cameras]
        watched = getattr(operator, "cameras", ())  # an operator who judges by sight
        cameras += [c for c in watched if c not in cameras]
        self._cameras = tuple(cameras)
        real = s.robot == "ur"
        if real and not s.emulated and policy.config.kind == "state":
            raise SettingError(
                "init", "is a state policy, which reads object poses a real cell does not "
                "measure; start from an image policy"
            )  # fmt: skip
        robot = open_robot(
            ROBOTS[s.robot],
            self.task,
            effects=s.effects,
            seed=s.rl.seed,
            cameras=tuple(cameras),
            object_poses=not real or s.emulated,
            cell=self.cell,
            emulated=s.emulated,
        )
        try:
            device = None
            if s.teleop is not None:
                device = open_teleop(
                    s.teleop,
                    self.cell.teleop if self.cell is not None else None,
                    terminal=terminal,
                    privileged=robot.privileged,
                    seed=s.rl.seed + 7,
                    watch=s.operator,
                )
            sets_up = real and not s.emulated  # a person sets a real cell up
            if device is not None or terminal is not None or sets_up:
                self.person = PersonInLoop(device, terminal, sets_up=sets_up, on_wait=on_wait)
                operator = self.person.operator or operator
            self.operator = operator
            if operator is not None:
                robot = OperatorTakeover(robot, operator, self.task)
        except BaseException:
            robot.close()
            raise
        if policy.config.grasp_hold:
            robot = GraspHold(robot)
        return robot

    def _judge(self) -> Judge:
        """One episode's judge of success: ground truth, the person's key, or the
        classifier (over ``success_frames`` successive observations)."""
        if self.settings.success == "key":
            assert self.person is not None  # checked_classifier: a terminal or a device
            return self.person.key_judge
        judge = (
            self.classifier.episode_judge(self.settings.success_frames)
            if self.classifier is not None
            else privileged_success(self.robot)
        )
        return self.person.watching(judge) if self.person is not None else judge

    # ------------------------------------------------------------ lifecycle
    @classmethod
    def start(
        cls,
        settings: RealRLSettings,
        operator: Operator | None = None,
        terminal: TerminalKeys | None = None,
        on_wait: Callable[[str], None] | None = None,
        on_notice: Callable[[str], None] | None = None,
    ) -> RealRL:
        """Start a run (``terminal``: the person's keys; ``on_wait``: told what the
        person is waited for, on a real cell; ``on_notice``: told when a learner apart
        is lost, back or behind, else a :class:`~twinrl_learn.remote_learner.
        LearnerWarning`)."""
        if not settings.init:
            raise SettingError(
                "init", "is needed to start a run: a policy checkpoint to start from"
            )
        classifier = checked_classifier(settings, terminal)  # fail before anything is written
        if settings.targets:
            load_targets(settings.targets)  # fail before anything is written
        policy = Policy.from_pretrained(settings.init, settings.device)
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
        operator = _operator(settings, operator)
        return cls(settings, run, operator, terminal, on_wait, classifier, on_notice)

    @classmethod
    def resume(
        cls,
        settings: RealRLSettings,
        operator: Operator | None = None,
        terminal: TerminalKeys | None = None,
        on_wait: Callable[[str], None] | None = None,
        on_notice: Callable[[str], None] | None = None,
    ) -> RealRL:
        """Continue the run in ``settings.out`` with the RL settings it started with."""
        out = Path(settings.out)
        if not (out / RUN_FILE).is_file():
            raise LearnError(f"{out / RUN_FILE} does not exist: there is no run to resume")
        device = resolve_device(settings.device)
        policy = Policy.from_pretrained(out / "agent", device)
        settings.rl = RLConfig.load(out / "agent")
        demo, twin = _buffers(settings, policy)
        classifier = checked_classifier(settings, terminal)
        # A learner apart holds the episodes: the actor keeps them in its session only.
        run = OnlineRun.resume(out, demo, twin, device, fill=not settings.learner)
        operator = _operator(settings, operator)
        return cls(settings, run, operator, terminal, on_wait, classifier, on_notice)

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
            if settings.learner:  # apart: it pretrains, or resumes, in its own folder
                self._learner = RemoteLearner(
                    run, learner_spec(settings, run), settings.learner,
                    sync=settings.learner_sync, timeout_s=settings.learner_timeout, say=self._say,
                )  # fmt: skip
                self.actor.load_state_dict(run.agent.policy.state_dict())
                self.checkpoint()
            else:
                if run.agent.updates < run.agent.config.offline_steps and not run.history:
                    run.pretrain(on_update)
                    self.actor.load_state_dict(run.agent.policy.state_dict())
                    self.checkpoint()
                self._learner = Learner(run)
            if not self.evaluations:
                self.evaluate()
                self.checkpoint()
            while run.agent.env_steps < settings.plant_steps:
                if self.person is not None:
                    self.person.poll()  # a pause pressed between episodes
                if self.paused:
                    break
                episode_index = len(run.history)
                if self._refresh_due(episode_index):
                    self.refresh_targets(episode_index)
                config, region, origin = self.resets.next(self.rng)
                try:
                    record = self.episode(config, region, origin)
                except RunPaused:
                    break  # nothing of the episode was recorded; its reset is drawn again
                self.checkpoint()  # before an evaluation: a learner apart already holds it
                if self._evaluation_due():
                    self.evaluate()
                    self.checkpoint()
                if on_episode is not None:
                    on_episode(record, self)
            if self.paused:
                return run
            if self.evaluations[-1].plant_steps != run.agent.env_steps:
                self.evaluate()
                self.checkpoint()
        finally:
            self.close()
            write_text_atomic(
                self.out / TIMING_FILE, json.dumps(loop_timing(self.periods), indent=1)
            )
        plot_evaluations(
            self.evaluations, self.out / "curve.png", title=f"real RL: {self.task.name}"
        )
        return run

    @property
    def learner(self) -> Learner | RemoteLearner | None:
        """The learner of a running run: a thread here, or apart (``settings.learner``)."""
        return self._learner

    @property
    def paused(self) -> bool:
        """Whether the person paused the run (it stops after the episode; resume goes on)."""
        return self.person is not None and self.person.pause_requested

    def close(self) -> None:
        if self._learner is not None:
            self._learner.close()
            self._learner = None
        self.robot.close()
        if self.person is not None:
            self.person.close()
        if self.view is not None:
            self.view.close()
            self.view = None

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
            operator=self._operator_name(),
        )
        person, view = self.person, self.view
        if person is not None:
            person.begin()

        def ready(observation: dict[str, np.ndarray]) -> None:
            """The reset's guidance, then (a real cell) the person sets it up and starts."""
            if view is not None:
                view.guidance(len(run.history), config, observation)
                view.note(f"{origin} reset in {region}")
            if person is not None:
                showing = None if view is None else lambda: view.live(self.robot.observe())
                person.ready(observation, showing)

        def on_step(_t: int, sent: Sent) -> None:
            learner.grant(1)
            if view is not None and self.source.observation is not None:
                view.step(self.source.observation, sent)

        outcome = run_episode(
            self.robot,
            self.source,
            self.task,
            config,
            judge=self._judge(),
            recorder=Recorder(run.session),
            meta=meta,
            on_step=on_step,
            until=person.until if person is not None else None,
            ready=ready,
        )
        self.periods.extend(outcome.periods)
        if self.settings.learner_sync:
            learner.wait()
        assert outcome.path is not None
        episodes = learner.add_episodes([outcome.path])
        self.actor.load_state_dict(learner.weights())
        run.extra.setdefault("reset_origins", []).append(origin)
        return run.record_round(episodes, learner.metrics)

    def _operator_name(self) -> str | None:
        if isinstance(self.operator, SimulatedOperator):
            return "simulated"
        if self.person is not None and self.person.teleop is not None:
            return self.person.teleop.kind
        return None

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
                twin=self.cell.twin if self.cell is not None else s.twin,  # the cell's own
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
        """Evaluate the deterministic policy on the fixed grid in a separate plant; on a
        UR cell, the success of the run's own episodes since the last point instead (a
        grid of evaluation episodes on the arm would cost the person's time)."""
        s, steps = self.settings, self.run_state.agent.env_steps
        if s.robot == "ur":
            last = self.evaluations[-1].plant_steps if self.evaluations else -1
            since = [r for r in self.run_state.history if r.env_steps > last]
            totals = {r: (wins, n) for r, (wins, n) in region_counts(since).items() if n}
            rates = {r: wins / n for r, (wins, n) in totals.items()}
            return self._add_point(steps, rates, 0, {r: n for r, (_, n) in totals.items()})
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
        return self._add_point(
            steps, report.success_rate(), report.episodes, report.region_episodes()
        )

    def _add_point(
        self, steps: int, rates: dict[str, float], episodes: int, per_region: dict[str, int]
    ) -> EvalPoint:
        point = EvalPoint(
            plant_steps=steps,
            plant_minutes=steps / self.robot.control_hz / 60,
            success_rate=rates,
            episodes=episodes,
            region_episodes=per_region,
        )
        self.evaluations.append(point)
        evaluations = [asdict(p) for p in self.evaluations]
        write_text_atomic(self.out / EVALUATIONS_FILE, json.dumps(evaluations, indent=1))
        return point


def checked_classifier(
    settings: RealRLSettings, terminal: TerminalKeys | None
) -> RewardClassifier | None:
    """The reward classifier that judges success, if any; a judge that cannot work is
    refused before anything is written (a key judge without keys or a device, a
    classifier of another task)."""
    if settings.success == "key" and settings.teleop is None and terminal is None:
        raise SettingError("success", "key needs the person's keys or device; run in a terminal")
    if settings.classifier is None:
        return None
    classifier = RewardClassifier.load(settings.classifier)
    task = task_class(settings.task).name
    if classifier.task != task:
        raise SettingError("classifier", f"judges {classifier.task}, not {task}")
    return classifier


def _operator(settings: RealRLSettings, operator: Operator | None) -> Operator | None:
    """The operator given, else the simulated one where the cell lends it the ground
    truth and no person's device is named (a device's operator is opened with it); with
    ``operator_sees``, the simulated one that judges from a pose estimator's view."""
    simulated = settings.robot == "plant" or settings.emulated
    if operator is not None or settings.operator is None or settings.teleop or not simulated:
        return operator
    seed = settings.rl.seed + 7
    if settings.operator_sees is not None:
        estimator = PoseEstimator.from_pretrained(settings.operator_sees, settings.device)
        return SeeingOperator(estimator, settings.operator, seed=seed)
    return SimulatedOperator(settings.operator, seed=seed)
