"""The ``twinrl`` command: the root app, assembled from each package's commands."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.console import Console
from rich.table import Table

# Only what the options' help texts and defaults need loads here, so that `twinrl --help`
# is quick; each command loads the rest (torch, the simulator, the datasets) when it runs.
from twinrl_data import cli as data_cli
from twinrl_data.console import progress, quiet_encoders
from twinrl_data.errors import TwinrlError, UsageError
from twinrl_learn.replay import RewardSettings
from twinrl_learn.settings import DEFAULTS, METHODS, RLConfig, SFTConfig
from twinrl_robot import cli as robot_cli
from twinrl_robot.operator import OperatorRule
from twinrl_sim import cli as sim_cli
from twinrl_sim.tasks import TASKS, make_task

if TYPE_CHECKING:
    from twinrl_learn.studies.pipeline import RunProgress

app = typer.Typer(
    help="twinrl: digital-twin-guided reinforcement learning for real robot arms.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
sim_cli.app.command("expert")(robot_cli.expert)
sim_cli.app.command("excite")(robot_cli.excite)
app.add_typer(sim_cli.app, name="sim")
app.add_typer(sim_cli.gap_app, name="gap")
app.add_typer(sim_cli.twin_app, name="twin")
data_cli.app.command("import-csv")(sim_cli.import_csv_command)  # needs the twin for FK
app.add_typer(data_cli.app, name="data")
app.command("view")(sim_cli.view)
app.command("expand")(sim_cli.expand_command)

train_app = typer.Typer(help="Train policies: SFT, twin RL, real RL.", no_args_is_help=True)
app.add_typer(train_app, name="train")
console = Console(soft_wrap=True)  # paths and figures are never broken across lines


@train_app.command("sft")
def train_sft_command(
    dataset: Annotated[
        list[Path], typer.Option(help="LeRobotDataset folder; repeat to mix datasets.")
    ],
    out: Annotated[
        Path, typer.Option(help="Checkpoint folder to create (or continue with --resume).")
    ],
    policy: Annotated[
        str, typer.Option(help="vla (cameras + language + proprio) or state (privileged).")
    ] = "vla",
    weights: Annotated[
        str | None,
        typer.Option(
            help="Sampling weight per --dataset, e.g. 1,2 (default: by their frames, as if "
            "they were one dataset; a resumed run keeps its own)."
        ),
    ] = None,
    steps: Annotated[
        int | None,
        typer.Option(
            help=f"Training steps (default: {DEFAULTS['vla'].steps} vla, "
            f"{DEFAULTS['state'].steps} state; a resumed run: its own, more extends it)."
        ),
    ] = None,
    batch_size: Annotated[
        int | None, typer.Option(help="Batch size (default by policy; a resumed run: its own).")
    ] = None,
    lr: Annotated[
        float | None,
        typer.Option(help="Learning rate (default by policy; a resumed run: its own)."),
    ] = None,
    lr_schedule: Annotated[
        str | None,
        typer.Option(
            help="cosine (the rate decays towards zero at the end of the run) or constant "
            "(default: cosine for state, constant for vla; a resumed run keeps its own)."
        ),
    ] = None,
    chunk: Annotated[
        int, typer.Option(help="Actions predicted and executed per look (action chunking).", min=1)
    ] = 8,
    inputs: Annotated[
        str,
        typer.Option(
            help="State policy only: absolute (object poses in the base frame, joint angles) "
            "or relative (objects relative to the TCP and tool; evens out generalisation "
            "from few demos)."
        ),
    ] = "absolute",
    image_size: Annotated[
        int, typer.Option(help="vla only: image size the cameras are resized to, 64 or 128.")
    ] = SFTConfig.image_size,
    locate_weight: Annotated[
        float,
        typer.Option(
            help="vla only: weight of the auxiliary loss that locates the objects relative to "
            "the TCP from the images (needs object poses in the data; 0 turns it off).",
            min=0.0,
        ),
    ] = SFTConfig.locate_weight,
    seed: Annotated[int, typer.Option(help="Seed (initialisation, sampling, augmentation).")] = 0,
    resume: Annotated[
        bool, typer.Option(help="Continue the run in --out exactly where it stopped.")
    ] = False,
) -> None:
    """Supervised fine-tuning on demonstrations (real and twin), with a loss curve."""
    from twinrl_learn.sft import train_sft

    if policy not in DEFAULTS:
        raise UsageError(f"--policy must be one of {', '.join(DEFAULTS)}, got '{policy}'")
    parsed = [float(w) for w in weights.split(",")] if weights else None
    config = SFTConfig(  # checks --inputs against --policy
        datasets=[str(d) for d in dataset],
        out=str(out),
        policy=policy,
        weights=parsed,
        steps=steps,
        batch_size=batch_size,
        lr=lr,
        lr_schedule=lr_schedule,
        chunk=chunk,
        inputs=inputs,
        image_size=image_size,
        locate_weight=locate_weight,
        seed=seed,
    )
    missing = [str(d) for d in dataset if not (d / "meta" / "info.json").is_file()]
    if missing:
        raise UsageError(f"--dataset {missing[0]} is not a LeRobotDataset (no meta/info.json)")
    with progress("loss", "rate") as bar:
        # A resumed run without --steps reports its own length.
        total = None if resume and steps is None else steps or DEFAULTS[policy].steps
        job = bar.add_task(f"SFT {policy}", total=total, loss="-", rate="-")

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
    if policy == "vla" and locate_weight > 0 and not result.locating:
        console.print(
            "note: no dataset holds both the object poses (observation.environment_state) "
            "and the TCP pose (tcp.x), so the policy learnt from the actions alone, "
            "without locating the objects"
        )


def _grid(text: str, flag: str = "--grid") -> tuple[int, int]:
    try:
        rows, cols = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UsageError(f"{flag} must look like 8x8, got '{text}'") from None
    if rows < 1 or cols < 1:
        raise UsageError(f"{flag} needs positive sizes, got '{text}'")
    return rows, cols


@app.command("eval")
def eval_command(
    checkpoint: Annotated[
        str, typer.Argument(help="twinrl checkpoint, lerobot pretrained_model folder, or 'expert'.")
    ],
    task: Annotated[str, typer.Option(help=f"Task: {', '.join(TASKS)}.")],
    out: Annotated[Path, typer.Option(help="Folder for episodes, eval.json and heatmap.png.")],
    world: Annotated[str, typer.Option(help="twin or plant.")] = "twin",
    effects: Annotated[Path | None, typer.Option(help="Hidden effects YAML for the plant.")] = None,
    grid: Annotated[
        str, typer.Option(help="Grid of target positions over ID and OOD, e.g. 8x8.")
    ] = "8x8",
    episodes: Annotated[int, typer.Option(help="Episodes per grid cell.", min=1)] = 1,
    seed: Annotated[int, typer.Option(help="Seed for object placement and sampling.")] = 0,
    open_loop: Annotated[
        bool,
        typer.Option(
            help="Run a twinrl policy's action chunks open-loop instead of averaging every "
            "prediction for each step (temporal ensembling)."
        ),
    ] = False,
    grasp_hold: Annotated[
        bool | None,
        typer.Option(
            help="Hold a twinrl policy's arm while the gripper closes, or not (default: as "
            "the checkpoint says; checkpoints hold)."
        ),
    ] = None,
) -> None:
    """Roll a policy out over a grid covering ID and OOD; success per region and a heatmap."""
    from twinrl_learn.evaluate import evaluate
    from twinrl_learn.runners import load_runner

    if task not in TASKS:
        make_task(task)  # raises with the nearest task name
    if world not in ("twin", "plant"):
        raise UsageError(f"--world must be twin or plant, got '{world}'")
    if world == "twin" and effects is not None:
        raise UsageError("--effects applies to --world plant only")
    if effects is not None and not effects.is_file():
        raise UsageError(f"--effects {effects} does not exist")
    runner = load_runner(checkpoint, open_loop=open_loop, grasp_hold=grasp_hold)
    with progress("success") as bar:
        job = bar.add_task(f"{runner.name} in the {world}", total=None, success="0")
        done = {"n": 0, "ok": 0}

        def advance(cell, success: bool) -> None:
            done["n"] += 1
            done["ok"] += success
            bar.update(job, advance=1, success=f"{done['ok']}/{done['n']}")

        report = evaluate(
            runner,
            task,
            world=world,
            effects=effects,
            grid=_grid(grid),
            episodes=episodes,
            seed=seed,
            out=out,
            on_episode=advance,
        )
    table = Table("region", "success", "episodes", title=f"{task}: {runner.name} in the {world}")
    for region, rate in report.success_rate().items():
        count = sum(c.episodes for c in report.cells if c.region == region)
        table.add_row(region, f"{100 * rate:.0f} %", str(count))
    console.print(table)
    console.print(f"{out / 'eval.json'}, {out / 'heatmap.png'}, episodes in {out / 'session'}")


def _sources(texts: list[str]) -> dict[str, Path]:
    """``LABEL=PATH`` or ``PATH`` (labelled by its folder name, or a session's by its
    parent's) -> {label: path}. A path that exists is a path, even with an ``=`` in it."""
    sources: dict[str, Path] = {}
    for text in texts:
        named = "=" in text and not Path(text).exists()
        label, path = text.split("=", 1) if named else ("", text)
        path = Path(path)
        label = label or (path.parent.name if path.name == "session" else path.name)
        if not path.exists():
            raise UsageError(
                f"{path} does not exist (give a session, .mcap, catalog or LeRobot dataset)"
            )
        if label in sources:
            raise UsageError(f"two sources are labelled '{label}'; name them LABEL=PATH")
        sources[label] = path
    return sources


@app.command("locate")
def locate_command(
    checkpoint: Annotated[Path, typer.Argument(help="twinrl image-policy checkpoint.")],
    sources: Annotated[
        list[str],
        typer.Argument(
            help="Episodes to replay: session folders (e.g. an eval's OUT/session), .mcap "
            "files, catalog .parquet files or LeRobot datasets, each PATH or LABEL=PATH."
        ),
    ],
    out: Annotated[Path, typer.Option(help="Folder for locating.json and locating.png.")],
) -> None:
    """How far off an image policy's locating head sees the objects in logged episodes.

    By the TCP's distance to each object, per source and region: its training demos
    against its own rollouts, say."""
    from twinrl_learn.locating import band_labels, locating_errors

    labelled = _sources(sources)
    with progress() as bar:
        job = bar.add_task("replaying episodes", total=None)
        report = locating_errors(
            checkpoint,
            labelled,
            out,
            on_episode=lambda _: bar.update(job, advance=1),
            on_start=lambda total: bar.update(job, total=total),
        )
    bands = band_labels(report["bands_cm"])
    table = Table(
        "source",
        "region",
        "object",
        "first frame",
        *[f"{b} cm" for b in bands],
        title=f"median planar locating error (cm) by TCP-to-object distance: {checkpoint.name}",
    )
    for label, regions in report["sources"].items():
        for region, objects in regions.items():
            for name, errors in objects.items():
                cells = ["–" if m is None else f"{m:.1f}" for m in errors["median_cm"]]
                table.add_row(label, region, name, f"{errors['first_frame_cm']:.1f}", *cells)
    console.print(table)
    console.print(f"{out / 'locating.json'}, {out / 'locating.png'}")


# Options shared by the RL commands (twin-rl, real-rl).
MethodOption = Annotated[str, typer.Option(help=f"Objective: {', '.join(METHODS)}.")]
BetaOption = Annotated[float | None, typer.Option(help="Weight of the imitation term.")]
EtaOption = Annotated[float | None, typer.Option(help="Weight of the Q term.")]
UtdOption = Annotated[float | None, typer.Option(help="Updates per environment (robot) step.")]
OfflineStepsOption = Annotated[
    int | None, typer.Option(help="Offline (Cal-QL + BC) updates before the first rollout.")
]
ExplorationOption = Annotated[
    float | None,
    typer.Option(help="Rollout spread as a multiple of the policy's (default 0.3; SAC 1)."),
]
ActorLrOption = Annotated[
    float | None,
    typer.Option(help="Actor learning rate (default 3e-5 fine-tuning an SFT policy; SAC 3e-4)."),
]
ResumeOption = Annotated[
    bool, typer.Option(help="Continue the run in --out from its last checkpoint.")
]


def _rl_config(method: str, **options) -> RLConfig:
    if method not in METHODS:
        raise UsageError(f"--method must be one of {', '.join(METHODS)}, got '{method}'")
    return RLConfig.for_method(method, **{k: v for k, v in options.items() if v is not None})


@train_app.command("twin-rl")
def train_twin_rl_command(
    task: Annotated[str, typer.Option(help=f"Task: {', '.join(TASKS)}.")],
    out: Annotated[Path, typer.Option(help="Run folder to create (or continue with --resume).")],
    init: Annotated[
        Path | None, typer.Option(help="SFT checkpoint to start from (not needed with --resume).")
    ] = None,
    demos: Annotated[
        list[Path] | None,
        typer.Option(help="LeRobotDataset(s) for the demo buffer (the SFT data); repeatable."),
    ] = None,
    envs: Annotated[int, typer.Option(help="Parallel twin environments.", min=1)] = 8,
    steps: Annotated[int, typer.Option(help="Twin environment steps in all.", min=1)] = 8000,
    method: MethodOption = "twinrl",
    beta: BetaOption = None,
    eta: EtaOption = None,
    utd: UtdOption = None,
    offline_steps: OfflineStepsOption = None,
    demo_ratio: Annotated[
        float | None, typer.Option(help="Share of each batch from demos/interventions.")
    ] = None,
    exploration: ExplorationOption = None,
    actor_lr: ActorLrOption = None,
    failures: Annotated[
        int, typer.Option(help="Failed rollouts to add to the exported twin buffer (at most).")
    ] = 0,
    seed: Annotated[int, typer.Option(help="Seed (networks, configurations, sampling).")] = 0,
    resume: ResumeOption = False,
) -> None:
    """Stage II: online RL in parallel twin envs; exports the twin buffer that seeds real RL."""
    import torch

    from twinrl_learn.policy import is_checkpoint
    from twinrl_learn.twin_rl import TwinRLSettings, run_twin_rl

    make_task(task)
    if not resume and init is None:
        raise UsageError("--init SFT_CHECKPOINT is needed to start a run (or pass --resume)")
    if init is not None and not is_checkpoint(init):
        raise UsageError(
            f"--init {init} is not a twinrl policy checkpoint; train one with `twinrl train sft`"
        )
    missing = [str(d) for d in demos or [] if not (d / "meta" / "info.json").is_file()]
    if missing:
        raise UsageError(f"--demos {missing[0]} is not a LeRobotDataset (no meta/info.json)")
    if resume:
        rl = RLConfig.load(out / "agent")
    else:
        rl = _rl_config(
            method,
            beta=beta,
            eta=eta,
            utd=utd,
            offline_steps=offline_steps,
            demo_ratio=demo_ratio,
            exploration=exploration,
            actor_lr=actor_lr,
            seed=seed,
        )
    settings = TwinRLSettings(
        task=task,
        init=str(init or ""),
        out=str(out),
        demos=[str(d) for d in demos or []],
        envs=envs,
        steps=steps,
        failures=failures,
        rl=rl,
    )
    torch.set_num_threads(1)  # small networks: one thread is fastest beside the simulation
    quiet_encoders()
    with progress("ID", "OOD", "q") as bar:
        offline = bar.add_task("offline updates", total=rl.offline_steps, ID="", OOD="", q="")
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
            settings,
            resume=resume,
            on_round=on_round,
            on_update=lambda n: bar.update(offline, completed=n),
        )
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


@train_app.command("real-rl")
def train_real_rl_command(
    task: Annotated[str, typer.Option(help=f"Task: {', '.join(TASKS)}.")],
    out: Annotated[Path, typer.Option(help="Run folder to create (or continue with --resume).")],
    init: Annotated[
        Path | None,
        typer.Option(help="Policy to start from: SFT checkpoint or a twin-rl run's agent/."),
    ] = None,
    keep_critic: Annotated[
        bool,
        typer.Option(
            help="Keep the critic of the twin-rl agent given as --init (default: a new "
            "critic, which measured better)."
        ),
    ] = False,
    robot: Annotated[str, typer.Option(help="Robot to learn on: plant.")] = "plant",
    effects: Annotated[
        Path | None, typer.Option(help="The plant's hidden effects (YAML; default built in).")
    ] = None,
    demos: Annotated[
        list[Path] | None,
        typer.Option(help="Real demos (LeRobotDataset) for the demo buffer; repeatable."),
    ] = None,
    twin_buffer: Annotated[
        Path | None, typer.Option(help="Twin buffer from `train twin-rl` (seeds the replay).")
    ] = None,
    targets: Annotated[
        Path | None, typer.Option(help="targets.json from `twinrl mine` (else uniform resets).")
    ] = None,
    target_ratio: Annotated[
        float, typer.Option(help="Share of resets drawn from the mined targets.")
    ] = 0.7,
    refresh_every: Annotated[
        int,
        typer.Option(
            help="Episodes between re-minings of --targets in the twin (0: never).", min=0
        ),
    ] = 10,
    plant_steps: Annotated[
        int, typer.Option(help="Robot steps to learn for (10 Hz: 600 = 1 min).", min=1)
    ] = 6000,
    eval_every: Annotated[
        int, typer.Option(help="Robot steps between evaluations on a fixed grid.", min=0)
    ] = 600,
    eval_grid: Annotated[str, typer.Option(help="Evaluation grid over ID and OOD.")] = "4x4",
    eval_episodes: Annotated[
        int, typer.Option(help="Evaluation episodes per grid cell.", min=1)
    ] = 1,
    method: MethodOption = "twinrl",
    beta: BetaOption = None,
    eta: EtaOption = None,
    utd: UtdOption = None,
    offline_steps: OfflineStepsOption = None,
    exploration: ExplorationOption = None,
    actor_lr: ActorLrOption = None,
    operator: Annotated[
        bool, typer.Option(help="Simulated operator takes over when the policy strays.")
    ] = True,
    funnel: Annotated[
        float,
        typer.Option(
            help="Operator: metres across the object a closing gripper may be from the "
            "expert's grasp before it takes over (0: only when the policy stalls).",
            min=0.0,
        ),
    ] = OperatorRule.funnel,
    correct_within: Annotated[
        float,
        typer.Option(
            help="Operator: metres from the expert's grasp within which a low arm is "
            "corrected straight to it instead of backed off to the approach (0: never).",
            min=0.0,
        ),
    ] = OperatorRule.correct_within,
    takeover_reward: Annotated[
        float,
        typer.Option(
            help="Reward of the policy's last step before a takeover, which ends its "
            "stretch for the critic (a success earns 10)."
        ),
    ] = RewardSettings.takeover,
    learner_sync: Annotated[
        bool,
        typer.Option(
            help="Between episodes, wait for the learner (its own thread) to run every update "
            "the episode bought, so a seed gives the same run; off, take the weights it has "
            "reached. The robot loop never waits for an update either way."
        ),
    ] = True,
    seed: Annotated[int, typer.Option(help="Seed (networks, resets, sensor noise).")] = 0,
    resume: ResumeOption = False,
) -> None:
    """Stage III: human-in-the-loop RL on the robot with twin-mined resets."""
    import torch

    from twinrl_learn.mining import load_targets
    from twinrl_learn.policy import is_checkpoint
    from twinrl_learn.real_rl import RealRL, RealRLSettings

    make_task(task)
    if not resume and init is None:
        raise UsageError("--init CHECKPOINT is needed to start a run (or pass --resume)")
    if init is not None and not is_checkpoint(init):
        raise UsageError(f"--init {init} is not a twinrl policy checkpoint")
    for flag, path in [("--demos", d) for d in demos or []] + [("--twin-buffer", twin_buffer)]:
        if path is not None and not (path / "meta" / "info.json").is_file():
            raise UsageError(f"{flag} {path} is not a LeRobotDataset (no meta/info.json)")
    if targets is not None:
        load_targets(targets)
    # A resumed run keeps the RL settings it started with (RealRL.resume loads them).
    rl = (
        RLConfig()
        if resume
        else _rl_config(
            method,
            beta=beta,
            eta=eta,
            utd=utd,
            offline_steps=offline_steps,
            exploration=exploration,
            actor_lr=actor_lr,
            rewards=RewardSettings(takeover=takeover_reward),
            seed=seed,
        )
    )
    settings = RealRLSettings(
        task=task,
        init=str(init or ""),
        keep_critic=keep_critic,
        out=str(out),
        robot=robot,
        effects=str(effects) if effects else None,
        demos=[str(d) for d in demos or []],
        twin_buffer=str(twin_buffer) if twin_buffer else None,
        targets=str(targets) if targets else None,
        target_ratio=target_ratio,
        refresh_every=refresh_every,
        plant_steps=plant_steps,
        eval_every=eval_every,
        eval_grid=_grid(eval_grid, "--eval-grid"),
        eval_episodes=eval_episodes,
        operator=OperatorRule(funnel=funnel, correct_within=correct_within) if operator else None,
        learner_sync=learner_sync,
        rl=rl,
    )
    # Small networks: one thread each for the actor and the learner.
    torch.set_num_threads(1)
    quiet_encoders()
    job_run = RealRL.resume(settings) if resume else RealRL.start(settings)
    with progress("ID", "OOD", "interventions") as bar:
        offline = bar.add_task(
            "offline updates",
            total=job_run.run_state.agent.config.offline_steps,
            ID="",
            OOD="",
            interventions="",
        )
        job = bar.add_task("robot steps", total=plant_steps, ID="-", OOD="-", interventions=0)

        def on_episode(record, real) -> None:
            rates = real.evaluations[-1].success_rate
            bar.update(
                job,
                completed=min(record.env_steps, plant_steps),
                **{r: f"{100 * v:.0f} %" for r, v in rates.items()},
                interventions=sum(r.interventions for r in real.run_state.history),
            )

        run = job_run.run(
            on_episode=on_episode, on_update=lambda n: bar.update(offline, completed=n)
        )
    final = job_run.evaluations[-1]
    console.print(
        f"{out}: {run.agent.env_steps} robot steps ({final.plant_minutes:.1f} plant min), "
        f"{len(run.history)} episodes, "
        f"{sum(r.interventions for r in run.history)} intervention steps; evaluation "
        + ", ".join(f"{r} {100 * v:.0f} %" for r, v in final.success_rate.items())
    )
    console.print(f"policy {out / 'agent'}, curve {out / 'curve.png'}")


@app.command("demo")
def demo_command(
    task: Annotated[str, typer.Option(help=f"Task: {', '.join(TASKS)}.")] = "pick_place",
    preset: Annotated[
        str,
        typer.Option(
            help="smoke (every stage, minutes), quick (state policy, ~16 min) or paper "
            "(image policy; about 15 hours of RL updates on 2 cores: meant for a GPU)."
        ),
    ] = "quick",
    out: Annotated[Path, typer.Option(help="Folder for the report, logs and policies.")] = Path(
        "out/twinrl_demo"
    ),
    seeds: Annotated[
        str | None, typer.Option(help="Comma-separated seeds (default: the preset's three).")
    ] = None,
    inputs: Annotated[
        str | None,
        typer.Option(
            help="State policy's inputs: absolute or relative (see train sft; default: the "
            "preset's: relative in quick, absolute in smoke)."
        ),
    ] = None,
    workers: Annotated[
        int, typer.Option(help="Real-RL runs side by side, one process each.", min=1)
    ] = 2,
    resume: Annotated[
        bool, typer.Option(help="Continue a stopped run in --out (finished stages are kept).")
    ] = False,
) -> None:
    """The whole TwinRL pipeline in the plant, then its baselines; report.md and .json.

    The baselines (HiL-SERL, ConRFT-style and TwinRL without the twin buffer) run on
    the same plant and seeds."""
    import torch

    from twinrl_learn.studies.pipeline import run_demo
    from twinrl_learn.studies.presets import PRESETS

    make_task(task)
    if preset not in PRESETS:
        raise UsageError(f"--preset must be one of {', '.join(PRESETS)}, got '{preset}'")
    chosen = _int_list(seeds, "--seeds") if seeds else None
    torch.set_num_threads(1)
    quiet_encoders()
    with progress("ID", "OOD") as bar:
        jobs: dict[tuple[str, int], int] = {}
        steps = PRESETS[preset].plant_steps

        def on_progress(run: RunProgress) -> None:
            key = (run.method, run.seed)
            if key not in jobs:
                jobs[key] = bar.add_task(
                    f"{run.method}, seed {run.seed}", total=steps, ID="-", OOD="-"
                )
            bar.update(
                jobs[key],
                completed=min(run.plant_steps, steps),
                **{r: f"{100 * v:.0f} %" for r, v in run.success_rate.items()},
            )

        report = run_demo(
            task,
            preset,
            out,
            seeds=chosen,
            inputs=inputs,
            workers=workers,
            resume=resume,
            log=lambda text: bar.console.print(text),
            on_progress=on_progress,
        )
    table = Table("method", "min to 95 % ID", "min to 95 % OOD", "final ID", "final OOD", "interv.")
    for name, m in report["methods"].items():
        to95 = m["plant_minutes_to_95"]
        table.add_row(
            name,
            *("-" if to95[r] is None else f"{to95[r]:.1f}" for r in ("ID", "OOD")),
            *(f"{100 * m['final_success'][r]:.0f} %" for r in ("ID", "OOD")),
            str(m["interventions"]),
        )
    console.print(table)
    console.print(f"report: {out / 'report.md'}")


def _int_list(text: str, flag: str) -> tuple[int, ...]:
    try:
        return tuple(int(part) for part in text.split(","))
    except ValueError:
        raise UsageError(
            f"{flag} takes comma-separated integers, e.g. 0,1,2; got '{text}'"
        ) from None


@app.command("mine")
def mine_command(
    task: Annotated[str, typer.Option(help=f"Task: {', '.join(TASKS)}.")],
    policy: Annotated[str, typer.Option(help="Policy checkpoint (twinrl or lerobot).")],
    out: Annotated[Path, typer.Option(help="targets.json to write (evaluation goes beside).")],
    episodes_from: Annotated[
        Path | None,
        typer.Option(help="Catalog (Parquet) whose twin evaluations of --policy to reuse."),
    ] = None,
    tau: Annotated[
        float, typer.Option(help="Success below which a configuration is a target.")
    ] = 0.8,
    k: Annotated[int, typer.Option(help="How many targets to keep.", min=1)] = 20,
    grid: Annotated[str, typer.Option(help="Configuration grid over ID and OOD.")] = "8x8",
    episodes: Annotated[int, typer.Option(help="Twin episodes per grid cell.", min=1)] = 2,
    seed: Annotated[int, typer.Option(help="Seed for the evaluation.")] = 0,
) -> None:
    """Stage III support: where does the policy fail in the twin? Ranked reset targets."""
    from twinrl_learn.mining import mine
    from twinrl_learn.runners import load_runner

    make_task(task)
    runner = load_runner(policy)
    result = mine(
        runner,
        task,
        out=out,
        grid=_grid(grid),
        episodes=episodes,
        tau=tau,
        k=k,
        seed=seed,
        catalog=episodes_from,
    )
    table = Table("#", "region", "x", "y", "est. success", "score", title=f"targets (tau {tau})")
    for i, target in enumerate(result["targets"], 1):
        table.add_row(
            str(i),
            target["region"],
            f"{target['x']:.3f}",
            f"{target['y']:.3f}",
            f"{100 * target['estimated_success']:.0f} %",
            f"{target['score']:.2f}",
        )
    console.print(table)
    console.print(
        f"{len(result['targets'])} targets from {result['episodes']} twin episodes: {out}"
    )


bench_app = typer.Typer(help="Reproduce the paper's experiments.", no_args_is_help=True)
app.add_typer(bench_app, name="bench")


@bench_app.command("stage1")
def bench_stage1(
    out: Annotated[Path, typer.Option(help="Folder for datasets, policies, heatmaps, table1.md.")],
    tasks: Annotated[
        str, typer.Option(help="Comma-separated tasks.")
    ] = "pick_place,insert_hexagon",
    policies: Annotated[
        str, typer.Option(help="Comma-separated policy kinds: state, vla.")
    ] = "state",
    scale: Annotated[
        float, typer.Option(help="Multiply every demo count (0.1 for a smoke run).")
    ] = 1.0,
    grid: Annotated[str, typer.Option(help="Evaluation grid over ID and OOD.")] = "4x4",
    episodes: Annotated[int, typer.Option(help="Evaluation episodes per grid cell.", min=1)] = 4,
    seed: Annotated[int, typer.Option(help="Seed for demos, SFT and evaluation.")] = 0,
    vla_steps: Annotated[int | None, typer.Option(help="SFT steps of the image policy.")] = None,
    state_steps: Annotated[int | None, typer.Option(help="SFT steps of the state policy.")] = None,
    fit_look: Annotated[
        bool,
        typer.Option(
            help="Fit the twin's appearance (light, table colour) to the real demos' images "
            "(gap diagnose) and synthesize the twin demos in that look."
        ),
    ] = False,
    detours: Annotated[
        float,
        typer.Option(
            help="Share of the twin demos that first stray beside the object (see expand).",
            min=0.0,
            max=1.0,
        ),
    ] = 0.0,
    inputs: Annotated[
        str,
        typer.Option(
            help="The state policy's inputs: relative (objects seen from the TCP) or "
            "absolute (poses in the base frame)."
        ),
    ] = "relative",
) -> None:
    """TwinRL's Table I in the plant: real-only SFT vs real + twin ID/OOD demos."""
    from twinrl_learn.studies.table1 import Stage1Settings, run_stage1

    steps = {k: v for k, v in (("vla", vla_steps), ("state", state_steps)) if v}
    settings = Stage1Settings(
        tasks=tuple(t for t in tasks.split(",") if t),
        policies=tuple(p for p in policies.split(",") if p),
        scale=scale,
        grid=_grid(grid),
        episodes_per_cell=episodes,
        steps=steps,
        fit_look=fit_look,
        detours=detours,
        state_inputs=inputs,
        seed=seed,
    )
    quiet_encoders()
    run_stage1(settings, out, log=lambda line: console.print(line))
    console.print((out / "table1.md").read_text())


@bench_app.command("stages")
def bench_stages(
    run: Annotated[Path, typer.Argument(help="A `twinrl demo` run folder (Stage II done).")],
    out: Annotated[Path, typer.Option(help="Folder for stages.md, stages.json, stages.png.")],
    seeds: Annotated[
        str, typer.Option(help="Comma-separated seeds: one evaluation and offline phase each.")
    ] = "0,1,2,3,4",
    grid: Annotated[str, typer.Option(help="Evaluation grid over ID and OOD.")] = "8x8",
    episodes: Annotated[int, typer.Option(help="Evaluation episodes per grid cell.", min=1)] = 2,
    finals: Annotated[
        bool, typer.Option(help="Also measure the final policies of the run's TwinRL runs.")
    ] = True,
) -> None:
    """What each stage of a pipeline run adds, on many plant episodes per policy.

    Measures the Stage I and Stage II policies, the Stage II policy after the real-RL
    offline phase with and without the twin buffer, and the TwinRL runs' final
    policies, all on the same plant configurations (paired by seed)."""
    import torch

    from twinrl_learn.studies.stages import StagesSettings, measure_stages

    settings = StagesSettings(
        run=run,
        out=out,
        seeds=_int_list(seeds, "--seeds"),
        grid=_grid(grid),
        episodes=episodes,
        finals=finals,
    )
    torch.set_num_threads(1)
    quiet_encoders()
    with progress() as bar:
        task = bar.add_task("measuring", total=None)

        def on_evaluation(done: int, total: int, label: str) -> None:
            bar.update(task, completed=done, total=total, description=label)

        measure_stages(settings, on_evaluation=on_evaluation)
    console.print((out / "stages.md").read_text(), markup=False)


def main() -> None:
    """Entry point: the project's errors (bad input of any kind) become one red line and
    exit status 2; anything else is a bug and keeps its traceback."""
    try:
        app()
    except TwinrlError as err:
        Console(stderr=True).print(f"[red]error:[/red] {err}", highlight=False, soft_wrap=True)
        sys.exit(2)
