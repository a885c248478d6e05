"""Stage II: online RL in N parallel twin environments from the SFT policy.

Each round resets the ``envs`` batched twin environments (in this process, or split
into shards over worker processes or a Ray cluster: :mod:`twinrl_sim.sharded`, the
same run either way) to configurations drawn
uniformly over the task's regions (ID and OOD), rolls the current policy out (sampling
from its tanh-Gaussian, one action chunk at a time; the arm held while the gripper
closes when the policy's ``grasp_hold`` says so) and logs every rollout as an
episode (source ``twin_rl``); after every vector step the agent takes ``utd`` updates
per new environment step on RLPD batches of demos and online rollouts. A checkpoint
follows every round. At the end the **twin buffer** is exported: a LeRobotDataset of
the successful rollouts (failures only on request, capped, since TwinRL found that
random twin failures slow real RL down) that seeds Stage III's replay buffer.

Outputs (besides :mod:`twinrl_learn.online`'s)::

    out/twin_buffer/    LeRobotDataset: the rollouts that seed the real replay buffer
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from twinrl_data.errors import SettingError
from twinrl_data.executor import spreading_executor
from twinrl_data.lerobot_io import export_dataset
from twinrl_data.mcap_log import read_episode
from twinrl_data.recorder import Recorder
from twinrl_data.schema import step_record
from twinrl_learn.agent import Agent
from twinrl_learn.compute import resolve_device
from twinrl_learn.online import OnlineRun, RoundRecord, plot_curve
from twinrl_learn.policy import Policy
from twinrl_learn.replay import ReplayBuffer
from twinrl_learn.settings import RLConfig, TwinRLSettings
from twinrl_robot.wrappers import HoldRule
from twinrl_sim.batch import BatchEnv
from twinrl_sim.sharded import ShardedBatchEnv
from twinrl_sim.tasks import Progress, Task, make_task, task_on_twin


def load_demo_buffer(demos: list[str], policy: Policy, rl: RLConfig) -> ReplayBuffer:
    return ReplayBuffer.from_datasets(demos, rewards=rl.rewards, **policy.replay_views())


def run_twin_rl(
    settings: TwinRLSettings,
    *,
    resume: bool = False,
    on_round: Callable[[RoundRecord, OnlineRun], None] | None = None,
    on_update: Callable[[int], None] | None = None,
) -> OnlineRun:
    """Run (or continue) Stage II; returns the finished :class:`OnlineRun`."""
    device = resolve_device(settings.device)
    twin = None if settings.twin is None else task_on_twin(settings.task, settings.twin)
    task = make_task(settings.task, twin)
    for region in settings.regions:
        task.region(region)
    if resume:
        # A resumed run keeps the RL settings it started with.
        settings.rl = RLConfig.load(Path(settings.out) / "agent")
        policy = Policy.from_pretrained(Path(settings.out) / "agent", device)
        demo = load_demo_buffer(settings.demos, policy, settings.rl)
        run = OnlineRun.resume(settings.out, demo, device=device)
    else:
        if not settings.init:
            raise SettingError(
                "init", "is needed to start a run: a policy checkpoint to start from"
            )
        policy = Policy.from_pretrained(settings.init, device)
        demo = load_demo_buffer(settings.demos, policy, settings.rl)
        run = OnlineRun.start(settings.out, Agent(policy, settings.rl), demo)
        run.pretrain(on_update)
        run.checkpoint()
    cameras = tuple(policy.config.cameras) if policy.needs_images else ()
    with ExitStack() as stack:
        env = _environments(task, settings, cameras, stack)
        while run.agent.env_steps < settings.steps:
            episodes, metrics = _round(run, env, settings)
            record = run.record_round(episodes, metrics)
            run.checkpoint()
            if on_round is not None:
                on_round(record, run)
    plot_curve(run.history, run.out / "curve.png", title=f"twin RL: {task.name}")
    export_twin_buffer(run, settings.failures)
    return run


def _environments(
    task: Task, settings: TwinRLSettings, cameras: tuple[str, ...], stack: ExitStack
) -> BatchEnv | ShardedBatchEnv:
    """The run's ``envs`` environments: here, or in shards on the executor that
    ``workers`` and ``cluster`` ask for (closed with ``stack``)."""
    executor = spreading_executor(settings.workers, settings.cluster)
    if executor is None:
        env: BatchEnv | ShardedBatchEnv = BatchEnv(task, settings.envs, cameras=cameras)
    else:
        stack.enter_context(executor)
        env = ShardedBatchEnv(task, settings.envs, executor, cameras=cameras)
    stack.callback(env.close)
    return env


def _round(run: OnlineRun, env: BatchEnv | ShardedBatchEnv, settings: TwinRLSettings):
    """One episode per env, logged and learned from; returns (episodes, last metrics)."""
    task, agent, n = env.task, run.agent, env.num_envs
    regions = [settings.regions[int(run.rng.integers(len(settings.regions)))] for _ in range(n)]
    configs = [task.sample_config(run.rng, region) for region in regions]
    obs = env.reset([c.to_dict() for c in configs])
    names = env.contract_names()
    recorders = [Recorder(run.session) for _ in range(n)]
    for recorder, region, config in zip(recorders, regions, configs, strict=True):
        recorder.start_episode(
            task.episode_meta(
                source="twin_rl",
                world="twin",
                names=names,
                config=config,
                region=region,
                policy=f"rl:{agent.config.method}",
            )
        )
    saved: dict[int, Path] = {}  # by env: the buffers take them in env order
    active = np.ones(n, bool)
    success = np.zeros(n, bool)
    queues: list[list[np.ndarray]] = [[] for _ in range(n)]
    holds = [HoldRule() for _ in range(n)] if agent.policy.config.grasp_hold else None
    metrics: dict[str, float] = {}
    while active.any():
        need = [i for i in range(n) if active[i] and not queues[i]]
        if need:
            chunks = agent.policy.act_chunks(
                {k: v[need] for k, v in obs.items()},
                [task.instruction] * len(need),
                deterministic=False,
                std_scale=agent.config.exploration,
            )
            for i, chunk in zip(need, chunks, strict=True):
                queues[i] = list(chunk)
        proposed = np.zeros((n, agent.policy.config.action_dim), np.float32)
        stepping = np.flatnonzero(active)
        for i in stepping:
            proposed[i] = queues[i].pop(0)
        actions = proposed.copy()
        if holds is not None:
            for i in stepping:
                actions[i] = holds[i](obs["observation.state"][i], proposed[i])
        next_obs, _, terminated, truncated, info = env.step(actions)
        for i in stepping:
            done = bool(terminated[i] or truncated[i])
            success[i] = bool(terminated[i])
            reward = task.reward(Progress(success=success[i]), "sparse")
            recorders[i].add_frame(
                step_record(
                    {k: v[i] for k, v in obs.items()},
                    actions[i],
                    info["command.joint_target"][i],
                    reward,
                    done,
                    success[i],
                    action_policy=proposed[i],
                )
            )
            if done:
                saved[i] = recorders[i].save_episode(success=bool(success[i]))
                active[i] = False
        obs = next_obs
        metrics = run.learn(len(stepping)) or metrics
    return run.add_episodes([saved[i] for i in range(n)]), metrics


def export_twin_buffer(run: OnlineRun, failures: int) -> Path | None:
    """Export the successful twin rollouts (plus at most ``failures`` failed ones, the
    most recent) as ``out/twin_buffer``; returns its path, or None if nothing qualifies."""
    paths = run.session.episode_paths()
    entries = run.session.entries
    wins = [p for p, e in zip(paths, entries, strict=True) if e.get("success")]
    losses = [p for p, e in zip(paths, entries, strict=True) if not e.get("success")]
    chosen = wins + (losses[-failures:] if failures > 0 else [])
    if not chosen:
        return None
    root = run.out / "twin_buffer"
    # Derived from the session, which keeps every episode: a resumed run re-exports it.
    export_dataset((read_episode(p) for p in chosen), root, force=True)
    return root
