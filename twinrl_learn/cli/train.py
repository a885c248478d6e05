"""``twinrl train``: SFT, twin RL and real RL, their options derived from the settings
records (:class:`~twinrl_learn.settings.SFTConfig`,
:class:`~twinrl_learn.twin_rl.TwinRLSettings`,
:class:`~twinrl_learn.real_rl.RealRLSettings`, :class:`~twinrl_learn.settings.RLConfig`):
a field's docstring is its option's help."""

from __future__ import annotations

import inspect
import sys
from pathlib import Path
from typing import Annotated, Any

import typer

from twinrl_data.console import progress, quiet_encoders
from twinrl_data.settings_cli import options, settings_command
from twinrl_learn.cli.common import DeviceOption, console
from twinrl_learn.replay import RewardSettings
from twinrl_learn.settings import (
    PerceptionSettings,
    RealRLSettings,
    RLConfig,
    SFTConfig,
    TwinRLSettings,
)
from twinrl_robot.operator import OperatorRule

app = typer.Typer(
    help="Train policies (SFT, twin RL, real RL) and reward classifiers.", no_args_is_help=True
)

RESUME = inspect.Parameter(
    "resume",
    inspect.Parameter.KEYWORD_ONLY,
    annotation=Annotated[bool, typer.Option(help="Continue the run in --out where it stopped.")],
    default=False,
)
# The agent's settings a run's command line may change; the rest are the method's (None:
# the method's own value, see RLConfig.for_method).
RL_OPTIONS = (
    "method", "beta", "eta", "utd", "offline_steps", "exploration", "actor_lr", "critic_warmup",
    "critic_per_actor",
)  # fmt: skip
RL_DEFAULTS = {name: None for name in RL_OPTIONS if name != "method"}


def rl_settings(given: dict[str, Any]) -> RLConfig:
    """The agent's settings from the options given (those left out: the method's)."""
    rewards = RewardSettings(**{k: v for k, v in given.pop("rewards", {}).items()})
    chosen = {k: v for k, v in given.items() if v is not None}
    return RLConfig.for_method(chosen.pop("method"), rewards=rewards, **chosen)


# ------------------------------------------------------------------------------ sft
def sft(settings: dict[str, Any], resume: bool) -> None:
    from twinrl_learn.sft import train_sft

    config = SFTConfig(**settings)
    with progress("loss", "rate") as bar:
        # A resumed run without --steps reports its own length.
        steps = config.steps
        total = None if resume and steps is None else steps or config.defaults.steps
        job = bar.add_task(f"SFT {config.policy}", total=total, loss="-", rate="-")

        def report(step: int, metrics: dict[str, float]) -> None:
            bar.update(
                job,
                completed=step,
                total=metrics["steps"],
                loss=f"{metrics['loss']:.3f}",
                rate=f"{metrics['steps_per_s']:.0f}/s",
            )

        result = train_sft(config, resume=resume, progress=report)
    tail = result.losses[-50:]
    console.print(
        f"{result.out}: {result.steps} steps in {result.seconds:.0f} s, final loss "
        f"{sum(tail) / max(len(tail), 1):.3f}; curve {result.out / 'loss.png'}"
    )
    if (
        config.policy == "vla"
        and config.perception is None
        and config.locate_weight > 0
        and not result.locating
    ):
        console.print(
            "note: no dataset holds both the object poses (observation.environment_state) "
            "and the TCP pose (tcp.x), so the policy learnt from the actions alone, "
            "without locating the objects"
        )


SFT_FIELDS = (
    "datasets", "out", "policy", "weights", "steps", "batch_size", "lr", "lr_schedule",
    "chunk", "inputs", "image_size", "locate_weight", "perception", "seed", "device",
)  # fmt: skip
settings_command(
    app,
    "sft",
    options(SFTConfig, only=SFT_FIELDS, names={"datasets": "dataset"}),
    sft,
    help="Supervised fine-tuning on demonstrations (real and twin), with a loss curve.",
    extra=[RESUME],
)


# ------------------------------------------------------------------------ perception
def perception(settings: dict[str, Any]) -> None:
    from twinrl_learn.perception.training import train_estimator

    config = PerceptionSettings(**settings)
    quiet_encoders()
    with progress("loss", "held") as bar:
        features = bar.add_task("frozen features", total=None, loss="", held="")
        job = bar.add_task("training", total=config.steps, loss="-", held="-")

        def report(stage: str, done: int, total: int, metrics: dict[str, float]) -> None:
            if stage == "features":
                bar.update(features, completed=done, total=total)
                return
            bar.update(
                job, completed=done, loss=f"{metrics['loss']:.4f}", held=f"{metrics['held']:.4f}"
            )

        result = train_estimator(config, progress=report)
    console.print(
        f"{result.out}: {result.steps} steps in {result.seconds:.0f} s; held-out episodes "
        + "; ".join(
            f"{name} {e['planar_cm']:.1f} cm planar, {e['orientation_deg']:.0f} deg"
            for name, e in result.held_out_errors.items()
        )
        + f"; curve {result.out / 'loss.png'}"
    )


settings_command(
    app,
    "perception",
    options(PerceptionSettings, names={"datasets": "dataset"}),
    perception,
    help="Train a pose estimator for the image policy on twin episodes (true poses as "
    "labels), on a frozen ImageNet-pretrained encoder.",
)


# -------------------------------------------------------------------------- twin-rl
def twin_rl(settings: dict[str, Any], resume: bool) -> None:
    import torch

    from twinrl_learn.twin_rl import run_twin_rl

    # A resumed run keeps the RL settings it started with (run_twin_rl loads them).
    rl = settings.pop("rl")
    config = TwinRLSettings(**settings, rl=RLConfig() if resume else rl_settings(rl))
    torch.set_num_threads(1)  # small networks: one thread is fastest beside the simulation
    quiet_encoders()
    envs, steps = config.envs, config.steps
    with progress("ID", "OOD", "q") as bar:
        offline = bar.add_task(
            "offline updates", total=config.rl.offline_steps, ID="", OOD="", q=""
        )
        job = bar.add_task("twin steps", total=steps, ID="-", OOD="-", q="-")

        def on_round(record, run) -> None:
            rates = run.success_rates(4 * envs)
            bar.update(
                job,
                completed=min(record.env_steps, steps),
                **{r: f"{100 * rates[r]:.0f} %" for r in rates},
                q=f"{record.metrics.get('q', float('nan')):.2f}",
            )

        run = run_twin_rl(
            config,
            resume=resume,
            on_round=on_round,
            on_update=lambda n: bar.update(offline, completed=n),
        )
    out = Path(config.out)
    rates = run.success_rates(4 * envs)
    console.print(
        f"{out}: {run.agent.env_steps} twin steps, {run.agent.updates} updates; recent success "
        + ", ".join(f"{r} {100 * v:.0f} %" for r, v in rates.items())
    )
    buffer = out / "twin_buffer"
    console.print(
        f"policy {out / 'agent'}, curve {out / 'curve.png'}, "
        + (f"twin buffer {buffer}" if buffer.exists() else "no successful rollout to export")
    )


TWIN_RL_FIELDS = (
    "task", "out", "init", "demos", "envs", "steps", "twin", "failures", "device", "workers",
    "cluster",
)  # fmt: skip
settings_command(
    app,
    "twin-rl",
    [
        *options(TwinRLSettings, only=TWIN_RL_FIELDS, defaults={"init": ""}),
        *options(
            RLConfig,
            only=(*RL_OPTIONS, "demo_ratio", "seed"),
            prefix="rl",
            defaults={**RL_DEFAULTS, "demo_ratio": None},
        ),
    ],
    twin_rl,
    help="Stage II: online RL in parallel twin envs; exports the twin buffer that seeds real RL.",
    extra=[RESUME],
)


# -------------------------------------------------------------------------- real-rl
OPERATOR = inspect.Parameter(
    "operator",
    inspect.Parameter.KEYWORD_ONLY,
    annotation=Annotated[
        bool, typer.Option(help="Simulated operator takes over when the policy strays.")
    ],
    default=True,
)


def real_rl(settings: dict[str, Any], operator: bool, resume: bool) -> None:
    import torch

    from twinrl_robot.teleop import TerminalKeys

    # A resumed run keeps the RL settings it started with (RealRL.resume loads them).
    rl = settings.pop("rl")
    rule_values = settings.pop("operator")  # the rule's options, given with or without it
    rule = OperatorRule(**rule_values) if operator else None
    config = RealRLSettings(**settings, operator=rule, rl=RLConfig() if resume else rl_settings(rl))
    # Small networks: one thread each for the actor and the learner.
    torch.set_num_threads(1)
    quiet_encoders()
    terminal = TerminalKeys() if sys.stdin.isatty() else None  # the person's keys
    try:
        _real_rl(config, resume, terminal)
    finally:
        if terminal is not None:
            terminal.close()


def _real_rl(config: RealRLSettings, resume: bool, terminal: Any) -> None:
    from twinrl_learn.real_rl import RealRL

    steps = config.plant_steps
    with progress("ID", "OOD", "interventions") as bar:
        waiting = bar.add_task("", total=None, visible=False, ID="", OOD="", interventions="")

        def on_wait(message: str) -> None:
            bar.update(waiting, description=message, visible=True)

        start = RealRL.resume if resume else RealRL.start
        job_run = start(config, terminal=terminal, on_wait=on_wait, on_notice=bar.console.print)
        offline = bar.add_task(
            "offline updates",
            total=job_run.run_state.agent.config.offline_steps,
            ID="",
            OOD="",
            interventions="",
        )
        job = bar.add_task("robot steps", total=steps, ID="-", OOD="-", interventions=0)

        def on_episode(record, real) -> None:
            bar.update(waiting, visible=False)
            rates = real.evaluations[-1].success_rate
            bar.update(
                job,
                completed=min(record.env_steps, steps),
                **{r: f"{100 * v:.0f} %" for r, v in rates.items()},
                interventions=sum(r.interventions for r in real.run_state.history),
            )

        run = job_run.run(
            on_episode=on_episode, on_update=lambda n: bar.update(offline, completed=n)
        )
    final, out = job_run.evaluations[-1], Path(config.out)
    if job_run.paused:
        console.print(
            f"{out}: paused after {len(run.history)} episodes ({run.agent.env_steps} robot "
            "steps), everything kept; go on with the same command and --resume"
        )
        return
    console.print(
        f"{out}: {run.agent.env_steps} robot steps ({final.plant_minutes:.1f} plant min), "
        f"{len(run.history)} episodes, "
        f"{sum(r.interventions for r in run.history)} intervention steps; evaluation "
        + ", ".join(f"{r} {100 * v:.0f} %" for r, v in final.success_rate.items())
    )
    console.print(f"policy {out / 'agent'}, curve {out / 'curve.png'}")


REAL_RL_FIELDS = (
    "task", "out", "init", "keep_critic", "robot", "cell", "emulated", "teleop", "success",
    "classifier", "success_frames", "effects", "demos", "twin_buffer",
    "targets", "target_ratio", "refresh_every", "twin", "plant_steps", "eval_every", "eval_grid",
    "eval_episodes", "learner", "learner_folder", "learner_sync", "learner_timeout",
    "show_resets", "view", "device", "operator_sees",
)  # fmt: skip
settings_command(
    app,
    "real-rl",
    [
        *options(RealRLSettings, only=REAL_RL_FIELDS, defaults={"init": ""}),
        *options(RLConfig, only=(*RL_OPTIONS, "seed"), prefix="rl", defaults=RL_DEFAULTS),
        *options(OperatorRule, only=("funnel", "correct_within"), prefix="operator"),
        *options(
            RewardSettings,
            only=("takeover",),
            prefix="rl.rewards",
            names={"takeover": "takeover_reward"},
        ),
    ],
    real_rl,
    help="Stage III: human-in-the-loop RL on the robot with twin-mined resets (keys: s "
    "success, f failure, q pause after this episode; Enter starts one on a real cell).",
    extra=[OPERATOR, RESUME],
)


# ---------------------------------------------------------------- reward-classifier
@app.command("reward-classifier")
def reward_classifier(
    datasets: Annotated[
        list[Path],
        typer.Argument(help="Session folders, .mcap episodes or LeRobot datasets of one task."),
    ],
    out: Annotated[Path, typer.Option(help="Folder to create for the classifier and report.")],
    camera: Annotated[
        list[str] | None, typer.Option(help="Camera it looks at; repeat for several.")
    ] = None,
    image_size: Annotated[int, typer.Option(help="Pixels each camera is resized to.", min=16)] = 64,
    steps: Annotated[int, typer.Option(help="Training steps.", min=1)] = 1500,
    margin: Annotated[
        int, typer.Option(help="Frames before the succeeding step left out as ambiguous.", min=0)
    ] = 6,
    task: Annotated[
        str | None, typer.Option(help="Only this task's episodes (a session may hold several).")
    ] = None,
    heldout: Annotated[float, typer.Option(help="Share of episodes held out.")] = 0.25,
    encoder: Annotated[
        str,
        typer.Option(
            help="scratch (a small CNN trained on the frames) or pretrained (a frozen "
            "ImageNet encoder with a trained head; use --image-size 128)."
        ),
    ] = "scratch",
    seed: Annotated[int, typer.Option(help="Seed of the split and the training.")] = 0,
    device: DeviceOption = "auto",
) -> None:
    """Learn a task's success from its episodes' cameras (a reward for real RL on a cell
    without ground truth); reports held-out accuracy, precision, recall and mistakes."""
    from twinrl_learn.reward_classifier import (
        REPORT,
        ClassifierSettings,
        episodes_under,
        train_reward_classifier,
    )

    settings = ClassifierSettings(
        cameras=tuple(camera or ["front"]),
        image_size=image_size,
        margin=margin,
        heldout=heldout,
        steps=steps,
        encoder=encoder,
        seed=seed,
    )
    episodes = episodes_under(datasets, settings.cameras, task)
    with progress("loss") as bar:
        job = bar.add_task("reward classifier", total=steps, loss="-")
        report = train_reward_classifier(
            episodes,
            out,
            settings,
            progress=lambda step, loss: bar.update(job, completed=step, loss=f"{loss:.3f}"),
            device=device,
        )
    console.print(
        f"{out}: held out {report.heldout_frames} frames of {report.heldout_episodes} episodes: "
        f"accuracy {100 * report.accuracy:.1f} %, precision {100 * report.precision:.1f} %, "
        f"recall {100 * report.recall:.1f} %; report {out / REPORT}"
    )
