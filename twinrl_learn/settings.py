"""The settings records of SFT, RL, twin RL and real RL, with their defaults and checks.

They live apart from the networks (``sft``, ``agent``, ``policy``) so that the command
line can show their defaults, and refuse bad values, without loading torch.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import NamedTuple

from twinrl_data.errors import SettingError
from twinrl_data.executor import cluster_address
from twinrl_learn.compute import check_device
from twinrl_learn.errors import LearnError
from twinrl_learn.replay import RewardSettings
from twinrl_robot.operator import OperatorRule
from twinrl_sim.spec import SpecError
from twinrl_sim.tasks import REGION_NAMES, task_class, task_on_twin

INPUTS = ("absolute", "relative")


def check_inputs(inputs: str, kind: str) -> None:
    """Refuse ``inputs`` that are unknown or that the policy ``kind`` cannot have: the
    one check behind SFT, its CLI and the pipeline, made before any work starts."""
    if inputs not in INPUTS:
        raise SettingError("inputs", f"must be one of {', '.join(INPUTS)}, got '{inputs}'")
    if inputs != "absolute" and kind != "state":
        raise SettingError(
            "inputs",
            f"applies to the state policy only: {inputs} inputs need the state policy (the vla "
            "policy sees images)",
        )


class Defaults(NamedTuple):
    """The SFT settings of a policy kind that no option overrides."""

    steps: int
    batch_size: int
    lr: float
    lr_schedule: str  # one of LR_SCHEDULES


# Enough for 30-120 episodes in a few minutes on 2 cores. The state policy's final
# weights were a noisy iterate at a constant rate; the image policy's were better at one
# (docs/results/sft.md has the figures).
DEFAULTS = {
    "state": Defaults(steps=3000, batch_size=256, lr=1e-3, lr_schedule="cosine"),
    "vla": Defaults(steps=5000, batch_size=64, lr=5e-4, lr_schedule="constant"),
}
# The image policy's input sizes (the cameras record 128 px) and the stride of its
# encoders' first convolution for each: both reach 32x32 feature maps.
STEM_STRIDES = {64: 2, 128: 4}
IMAGE_SIZES = tuple(STEM_STRIDES)
# How the learning rate runs over the steps (see learning_rate).
LR_SCHEDULES = ("cosine", "constant")


@dataclass
class SFTConfig:
    """What to train on and how. ``None`` fields take the defaults of the policy kind, or
    in a resumed run the run's own settings."""

    datasets: list[str]
    """LeRobotDataset folder; repeat to mix datasets."""
    out: str
    """Checkpoint folder to create (or continue with resume)."""
    policy: str = "vla"
    """vla (cameras + language + proprio) or state (privileged)."""
    weights: list[float] | None = None
    """Sampling weight per dataset, e.g. 1,2 (default: by their frames, as if they were one
    dataset; a resumed run keeps its own)."""
    steps: int | None = None
    """Training steps (default: 5000 vla, 3000 state and vla with `perception`; a resumed
    run: its own, more extends it)."""
    batch_size: int | None = None
    """Batch size (default by policy, vla with `perception` as state; a resumed run: its
    own)."""
    lr: float | None = None
    """Learning rate (default by policy; a resumed run: its own)."""
    lr_schedule: str | None = None
    """cosine (the rate decays towards zero at the end of the run) or constant (default:
    cosine for state, constant for vla; a resumed run keeps its own)."""
    chunk: int = 8
    """Actions predicted and executed per look (action chunking)."""
    inputs: str = "absolute"
    """State policy only: absolute (object poses in the base frame, joint angles) or
    relative (objects relative to the TCP and tool; evens out generalisation from few
    demos)."""
    image_size: int = 128
    """vla only: image size the cameras are resized to, 64 or 128."""
    locate_weight: float = 10.0
    """vla only: weight of the auxiliary loss that locates the objects relative to the TCP
    from the images (needs object poses in the data; 0 turns it off). Its squared error is
    in decimetres (a 1 cm miss costs 0.01); 10 beat 1 and 30 (docs/results/defaults.md)."""
    perception: str | None = None
    """vla only: a pose estimator folder (`twinrl train perception`) the policy acts
    through: it reads the cameras and proprio and says where the objects are, and the
    policy acts on that as the state policy does on the true poses (no locating head)."""
    seed: int = 0
    """Seed (initialisation, sampling, augmentation)."""
    checkpoint_every: int = 500
    """Steps between checkpoints."""
    log_every: int = 25
    """Steps between progress reports."""
    device: str = "auto"
    """Where the networks run: auto (a GPU if torch sees one), cpu, cuda or cuda:N."""

    def __post_init__(self) -> None:
        check_device(self.device)
        if self.policy not in DEFAULTS:
            raise SettingError(
                "policy", f"must be one of {', '.join(DEFAULTS)}, got '{self.policy}'"
            )
        check_inputs(self.inputs, self.policy)
        if self.image_size not in IMAGE_SIZES:
            raise SettingError(
                "image_size",
                f"must be one of {', '.join(map(str, IMAGE_SIZES))}, got {self.image_size}",
            )
        if self.locate_weight < 0:
            raise SettingError("locate_weight", f"must be >= 0, got {self.locate_weight}")
        if self.perception is not None and self.policy != "vla":
            raise SettingError(
                "perception", "serves the vla policy (the state policy reads the true poses)"
            )
        if self.lr_schedule not in (None, *LR_SCHEDULES):
            raise SettingError(
                "lr_schedule",
                f"must be one of {', '.join(LR_SCHEDULES)}, got '{self.lr_schedule}'",
            )
        if self.chunk < 1:
            raise SettingError("chunk", f"must be at least 1, got {self.chunk}")

    @property
    def defaults(self) -> Defaults:
        """The defaults of the network this trains: an image policy acting through a pose
        estimator trains the state policy's network on its estimates, so it takes the
        state policy's."""
        return DEFAULTS["state" if self.perception is not None else self.policy]

    def resolved(self) -> SFTConfig:
        defaults = self.defaults
        return SFTConfig(
            **{
                **asdict(self),
                "steps": self.steps or defaults.steps,
                "batch_size": self.batch_size or defaults.batch_size,
                "lr": self.lr or defaults.lr,
                "lr_schedule": self.lr_schedule or defaults.lr_schedule,
            }
        )


@dataclass
class PerceptionSettings:
    """What the pose estimator learns from, and how long (twinrl_learn.perception)."""

    datasets: list[str]
    """Twin episodes holding the true object poses (LeRobot dataset, session or
    catalog); repeat to add more."""
    out: str
    """Folder for the estimator (must not exist or be empty)."""
    steps: int = 3000
    """Training steps."""
    batch_size: int = 256
    """Frames per step."""
    lr: float = 1e-3
    """Peak learning rate (cosine decay to zero)."""
    head_width: int = 64
    """Channels of each camera's trained head, a multiple of 8 (its 3x3 convolution is
    most of a step's time)."""
    seed: int = 0
    """Seed (initialisation, held-out episodes, sampling)."""
    log_every: int = 100
    """Steps between progress reports and held-out checks."""
    device: str = "auto"
    """Where the networks run: auto (a GPU if torch sees one), cpu, cuda or cuda:N."""

    def __post_init__(self) -> None:
        check_device(self.device)
        if not self.datasets:
            raise SettingError("datasets", "is empty; pass twin episodes that hold object poses")
        for name in ("steps", "batch_size", "log_every"):
            if getattr(self, name) < 1:
                raise SettingError(name, f"must be at least 1, got {getattr(self, name)}")
        if self.head_width < 8 or self.head_width % 8:
            raise SettingError("head_width", f"must be a multiple of 8, got {self.head_width}")
        if not self.lr > 0:
            raise SettingError("lr", f"must be > 0, got {self.lr}")


METHODS = ("twinrl", "conrft", "hil-serl")


@dataclass
class RLConfig:
    """Hyper-parameters of the agent (defaults: TwinRL's where the paper gives them)."""

    method: str = "twinrl"
    """Objective: twinrl, conrft or hil-serl (see for_method)."""
    gamma: float = 0.98
    """Discount per control step."""
    tau: float = 0.005
    """Soft update rate of the target critics."""
    critics: int = 2
    """Members of the critic ensemble."""
    hidden: int = 256
    """Width of the critics' hidden layers."""
    batch_size: int = 64
    """Transitions per update (as in the paper)."""
    actor_lr: float = 3e-5
    """Actor learning rate: small, since 3e-4 wore a fine-tuned SFT policy down in real RL
    (docs/results/defaults.md); SAC without an imitation term keeps 3e-4."""
    critic_lr: float = 3e-4
    """Critic learning rate."""
    beta: float = 1.0
    """Weight of the imitation term (L_IL)."""
    eta: float = 0.1
    """Weight of the Q term (L_Q); at 1 the young critic undid the SFT policy
    (docs/results/defaults.md)."""
    beta_online: float | None = None
    """Weight of the imitation term after the offline phase (None: unchanged)."""
    cql_alpha: float = 0.1
    """Weight of the Cal-QL regulariser in the offline phase."""
    cql_actions: int = 4
    """Sampled actions per state in the Cal-QL regulariser."""
    entropy: bool = False
    """SAC's temperature term in the actor and the TD target."""
    target_entropy_per_dim: float = -1.0
    """SAC's target entropy per action dimension."""
    temperature_init: float = 1.0
    """SAC's temperature at the start (with ``entropy``)."""
    critic_warmup: int = 0
    """Updates at the start in which only the critic learns: the actor moves once the
    critic has learnt something (HiL-SERL's recipe for a policy that starts good)."""
    critic_per_actor: int = 1
    """Critic updates per actor update (HiL-SERL's critic-to-actor ratio)."""
    demo_ratio: float = 0.5
    """Share of each batch from demos and interventions (RLPD)."""
    exploration: float = 0.3
    """Rollout spread as a multiple of the policy's: a spread learned by imitation from
    noisy teleop is too wide for millimetre tasks (SAC learns its own: 1.0)."""
    utd: float = 1.0
    """Gradient updates per environment (robot) step."""
    offline_steps: int = 500
    """Offline (Cal-QL + imitation) updates before the first rollout."""
    rewards: RewardSettings = field(default_factory=RewardSettings)
    """The reward of each step (see RewardSettings)."""
    seed: int = 0
    """Seed (networks, sampling, resets, sensor noise)."""

    def __post_init__(self) -> None:
        if isinstance(self.rewards, dict):
            self.rewards = RewardSettings(**self.rewards)
        if self.method not in METHODS:
            raise SettingError(
                "method", f"must be one of {', '.join(METHODS)}, got '{self.method}'"
            )
        if self.critics < 2:
            raise SettingError("critics", f"must be at least 2 (an ensemble), got {self.critics}")
        if not 0 <= self.demo_ratio <= 1:
            raise SettingError("demo_ratio", f"must be in [0, 1], got {self.demo_ratio}")
        for name in ("beta", "eta", "utd", "exploration"):
            if getattr(self, name) < 0:
                raise SettingError(name, f"must be >= 0, got {getattr(self, name)}")
        if self.offline_steps < 0:
            raise SettingError("offline_steps", f"must be >= 0, got {self.offline_steps}")
        if self.critic_warmup < 0:
            raise SettingError("critic_warmup", f"must be >= 0, got {self.critic_warmup}")
        if self.critic_per_actor < 1:
            raise SettingError(
                "critic_per_actor", f"must be at least 1, got {self.critic_per_actor}"
            )
        if not self.temperature_init > 0:
            raise SettingError("temperature_init", f"must be > 0, got {self.temperature_init}")

    @classmethod
    def load(cls, folder: str | Path) -> RLConfig:
        """The settings an RL checkpoint folder was trained with."""
        path = Path(folder) / "rl_config.json"
        if not path.is_file():
            raise LearnError(f"{folder} holds no rl_config.json; it is not an RL checkpoint")
        return cls(**json.loads(path.read_text()))

    @classmethod
    def for_method(cls, method: str, **overrides) -> RLConfig:
        """The settings that define each compared method. HiL-SERL's follow its authors'
        recipe: SAC with RLPD's half-demo batches, no imitation term, the temperature
        starting at 0.01, two critic updates per actor update and per robot step, and
        the critic warmed on the demos (the offline phase, actor still) before the actor
        moves (docs/results/real-rl.md)."""
        base: dict = {"method": method}
        if method == "hil-serl":
            base |= {
                "beta": 0.0,
                "eta": 1.0,
                "entropy": True,
                "temperature_init": 0.01,
                "cql_alpha": 0.0,
                "exploration": 1.0,
                "actor_lr": 3e-4,
                "utd": 2.0,
                "critic_per_actor": 2,
            }
            merged = base | overrides
            merged.setdefault("critic_warmup", merged.get("offline_steps", cls.offline_steps))
            return cls(**merged)
        return cls(**(base | overrides))


@dataclass
class TwinRLSettings:
    """What to run: ``steps`` twin environment steps in rounds of ``envs`` episodes."""

    task: str
    """Task (pick_place, insert_hexagon, insert_triple_column, erase_whiteboard)."""
    init: str
    """SFT checkpoint to start from (an RL checkpoint folder's policy works too)."""
    out: str
    """Run folder to create (or continue with resume)."""
    demos: list[str] = field(default_factory=list)
    """LeRobotDataset(s) for the demo buffer (the SFT data)."""
    envs: int = 8
    """Parallel twin environments."""
    steps: int = 8000
    """Twin environment steps in all."""
    regions: tuple[str, ...] = REGION_NAMES
    """Regions the configurations are drawn from."""
    twin: str | None = None
    """The twin to run in: a built-in cell or a scene spec file (e.g. the look `twinrl gap
    diagnose` fitted to the real demos' images, where an image policy's twin demos were
    made; default: the task's scene)."""
    failures: int = 0
    """Failed rollouts to add to the exported twin buffer (at most)."""
    device: str = "auto"
    """Where the networks run: auto (a GPU if torch sees one), cpu, cuda or cuda:N."""
    workers: int | None = None
    """Shards of the environments, each stepped by a worker (default: 1, in this process;
    on a cluster, one per CPU); the run is the same with any number."""
    cluster: str = ""
    """Where the shards run: none (this machine's worker processes), local, auto,
    HOST:PORT or ray://HOST:PORT (a Ray cluster's head); see docs/guides/scale-out.md."""
    rl: RLConfig = field(default_factory=RLConfig)
    """The agent's settings."""

    def __post_init__(self) -> None:
        check_device(self.device)
        task_class(self.task)  # an unknown task: the nearest name
        if self.workers is not None and self.workers < 1:
            raise SettingError("workers", f"must be at least 1, got {self.workers}")
        cluster_address(self.cluster)  # a bad address stops here, before anything runs
        for name in ("envs", "steps"):
            if getattr(self, name) < 1:
                raise SettingError(name, f"must be at least 1, got {getattr(self, name)}")
        if self.failures < 0:
            raise SettingError("failures", f"must be >= 0, got {self.failures}")
        if self.twin is not None:
            check_twin(self.task, self.twin)


def check_twin(task: str, twin: str) -> None:
    """A run's ``twin`` must be a cell that holds ``task``'s objects: a missing or wrong
    one stops the run before anything starts, naming the setting."""
    try:
        task_on_twin(task, twin)
    except SpecError as err:
        raise SettingError("twin", err.args[0]) from None


LEARNING_ROBOTS = ("plant", "ur")  # real RL learns on these (not the ideal twin)
SUCCESS_JUDGES = ("truth", "key", "classifier")


@dataclass
class RealRLSettings:
    """What to run: ``plant_steps`` robot steps of human-in-the-loop RL."""

    task: str
    """Task (pick_place, insert_hexagon, insert_triple_column, erase_whiteboard)."""
    init: str
    """Policy to start from: an SFT checkpoint or a twin-rl run's agent/ (not needed to
    resume)."""
    out: str
    """Run folder to create (or continue with resume)."""
    keep_critic: bool = False
    """Keep the critic of the twin-rl agent given as init (default: a new critic, which
    measured better: docs/results/defaults.md)."""
    robot: str = "plant"
    """Robot to learn on: plant, or ur (the UR arm of `cell`)."""
    cell: str | None = None
    """The UR cell's file (robot ur)."""
    emulated: bool = False
    """The UR cell is the emulator (`twinrl robot emulate`), which sets each reset up itself."""
    teleop: str | None = None
    """The person's device, to take over from the policy and hand back: spacemouse,
    gamepad[:/dev/input/eventN], keyboard, or scripted (the operator rule at a virtual
    device: plant and emulator only). Default: the simulated operator (plant and
    emulator), nobody on a real cell."""
    success: str = "truth"
    """Who judges an episode's success: truth (the plant's or emulator's ground truth),
    key (the person's s and f keys or device buttons) or classifier (`classifier`)."""
    classifier: str | None = None
    """A reward classifier from `twinrl train reward-classifier` (success classifier)."""
    success_frames: int = 1
    """Successive observations the classifier must call a success before it ends the
    episode (success classifier): 3 keeps a lone false positive from ending it."""
    effects: str | None = None
    """The plant's hidden effects (YAML; default: the built-in plant)."""
    demos: list[str] = field(default_factory=list)
    """LeRobotDataset(s) of real demos: the demo buffer; repeatable (with a learner
    apart, paths as the learner's machine sees them: it alone reads them)."""
    twin_buffer: str | None = None
    """Stage II's twin buffer (twin-rl's twin_buffer/): the replay buffer's start (read
    by the learner, as demos are)."""
    targets: str | None = None
    """targets.json from `twinrl mine` (default: uniform resets over the regions)."""
    target_ratio: float = 0.7
    """Share of resets drawn from the targets."""
    refresh_every: int = 10
    """Episodes between re-minings of the targets in the twin (0: never; without targets
    the resets stay uniform and nothing is mined)."""
    mining_grid: tuple[int, int] = (4, 4)
    """Grid of configurations the targets are mined over."""
    twin: str | None = None
    """The twin the targets are mined again in (plant only: a built-in cell or a scene spec
    file; default: the task's scene; a UR cell mines in its cell file's twin)."""
    mining_episodes: int = 1
    """Twin episodes per mining grid cell."""
    tau: float = 0.8
    """Mining: a cell whose estimated success is below this is a failure."""
    k: int = 20
    """Mining: targets kept."""
    plant_steps: int = 6000
    """Robot steps to learn for (10 Hz: 600 = 1 min)."""
    eval_every: int = 600
    """Robot steps between evaluations on a fixed grid (0: only at the start and end)."""
    eval_grid: tuple[int, int] = (4, 4)
    """Evaluation grid over ID and OOD."""
    eval_episodes: int = 1
    """Evaluation episodes per grid cell."""
    operator: OperatorRule | None = field(default_factory=OperatorRule)
    """When the simulated operator takes the controls (None: nobody does)."""
    show_resets: bool = True
    """Keep a live view in Rerun: each reset rendered from the cell's twin, with its
    outlines over the live cameras, then the cameras, joints and actions as they run."""
    view: str | None = None
    """Where the live view goes: ``spawn`` (a viewer), a ``rerun+http://`` URL, or an
    ``.rrd`` path (default: ``live-<first episode>.rrd`` in the run's folder)."""
    learner_sync: bool = True
    """Between episodes, wait for the learner (its own thread) to run every update the
    episode bought, so a seed gives the same run; off, take the weights it has reached.
    The robot loop never waits for an update either way."""
    learner: str = ""
    """Where the learner (buffers and updates) runs: empty, a thread of this process;
    ``process``, a process of its own on this machine; or a Ray cluster as `cluster`
    settings name one (local, auto, HOST:PORT, ray://HOST:PORT), e.g. a machine with a
    GPU. Apart, it is sent each episode and sends the weights back; when it is lost the
    robot goes on with the last weights (docs/guides/scale-out.md)."""
    learner_folder: str | None = None
    """The learner's own run folder, on its machine (default: ``learner/`` in ``out``)."""
    learner_timeout: float = 600.0
    """Seconds a learner apart may take to answer an episode (with ``learner_sync``, the
    updates it bought included), or to start again, before it is taken for lost: it is
    stopped, the robot goes on with the last weights, and a learner starts again from
    its folder after the next episode."""
    device: str = "auto"
    """Where the networks run: auto (a GPU if torch sees one), cpu, cuda or cuda:N."""
    operator_sees: str | None = None
    """A pose estimator (`twinrl train perception`): the simulated operator decides from
    where it sees the objects in the cameras, not from the plant's progress (a person's
    eyes, not the ground truth)."""
    rl: RLConfig = field(default_factory=RLConfig)
    """The agent's settings."""

    def __post_init__(self) -> None:
        check_device(self.device)
        task_class(self.task)  # an unknown task: the nearest name
        if self.operator_sees is not None and (self.operator is None or self.teleop):
            raise SettingError(
                "operator_sees", "is the simulated operator's eyes: not with a person's "
                "device (teleop) or without an operator"
            )  # fmt: skip
        if self.learner not in ("", "process"):
            try:
                cluster_address(self.learner)
            except SettingError:
                raise SettingError(
                    "learner", "must be empty (a thread here), process, or a Ray cluster: "
                    f"local, auto, HOST:PORT or ray://HOST:PORT; got '{self.learner}'"
                ) from None  # fmt: skip
        if self.learner_timeout <= 0:
            raise SettingError("learner_timeout", f"must be positive, got {self.learner_timeout}")
        if self.learner_folder is not None and not self.learner:
            raise SettingError("learner_folder", "is the folder of a learner apart; set `learner`")
        if self.robot not in LEARNING_ROBOTS:
            raise SettingError(
                "robot",
                f"{self.robot} is not available; use one of {', '.join(LEARNING_ROBOTS)}",
            )
        if self.robot == "ur" and self.cell is None:
            raise SettingError("cell", "a UR arm needs its cell file")
        if self.robot == "plant" and (self.cell is not None or self.emulated):
            raise SettingError("cell", "describes a UR arm; learn on it with `robot` ur")
        if self.robot == "ur" and self.twin is not None:
            raise SettingError("twin", "a UR cell is mined in its cell file's twin; leave it out")
        if self.twin is not None:
            check_twin(self.task, self.twin)
        if self.robot == "ur" and self.effects is not None:
            raise SettingError("effects", "apply to the plant only; a UR cell has its own physics")
        if self.success not in SUCCESS_JUDGES:
            raise SettingError(
                "success", f"must be one of {', '.join(SUCCESS_JUDGES)}, got {self.success}"
            )
        if self.view is not None and not (
            self.view == "spawn" or self.view.endswith(".rrd") or "://" in self.view
        ):
            raise SettingError(
                "view", f"must be spawn, a rerun+http:// URL or an .rrd path, got {self.view}"
            )
        if self.success == "truth" and self.robot == "ur" and not self.emulated:
            raise SettingError(
                "success",
                "truth needs ground truth, which a real cell lacks; use key or classifier",
            )
        if self.success == "classifier" and self.classifier is None:
            raise SettingError(
                "classifier", "is needed to judge success by it: train one with twinrl train "
                "reward-classifier"
            )  # fmt: skip
        if self.success != "classifier" and self.classifier is not None:
            raise SettingError("classifier", "is read only when `success` is classifier")
        if self.success_frames < 1:
            raise SettingError("success_frames", f"must be at least 1, got {self.success_frames}")
        if self.success != "classifier" and self.success_frames != 1:
            raise SettingError("success_frames", "is read only when `success` is classifier")
        if not 0 <= self.target_ratio <= 1:
            raise SettingError("target_ratio", f"must be in [0, 1], got {self.target_ratio}")
        for name in ("refresh_every", "eval_every"):
            if getattr(self, name) < 0:
                raise SettingError(name, f"must be >= 0, got {getattr(self, name)}")
        for name in ("plant_steps", "eval_episodes", "mining_episodes", "k"):
            if getattr(self, name) < 1:
                raise SettingError(name, f"must be at least 1, got {getattr(self, name)}")
