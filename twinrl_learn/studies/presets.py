"""The scales a pipeline run comes in (presets) and the methods it compares.

Why each preset is set as it is, with the measurements behind it, is in the docs
(``docs/results/pipeline-quick.md``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from twinrl_data.errors import SettingError
from twinrl_learn.settings import RLConfig


@dataclass(frozen=True)
class Preset:
    """The scale of a pipeline run."""

    policy: str  # state (privileged, fast) or vla (cameras + language)
    real_demos: int
    twin_id: int
    twin_ood: int
    twin_rl_steps: int
    twin_envs: int
    mining_grid: tuple[int, int]
    mining_episodes: int
    plant_steps: int  # per real-RL run (10 Hz: 600 = 1 plant minute)
    eval_every: int
    eval_grid: tuple[int, int]
    eval_episodes: int
    offline_steps: int
    refresh_every: int
    seeds: tuple[int, ...]
    sft_steps: int | None = None  # None: the SFT defaults of the policy kind
    inputs: str = "absolute"  # the state policy's inputs (twinrl_learn.policy)
    # What a real cell has instead of the plant's privileged state (all off: the plant's
    # truth judges success and drives the simulated person):
    fit_look: bool = False  # twin work in the look fitted to the real demos' images
    perception: int = 0  # vla: twin episodes per region a pose estimator learns from
    classifier_episodes: int = 0  # twin episodes per region a success classifier learns from
    success_frames: int = 1  # successive frames the classifier must call a success
    operator_sees: bool = False  # the simulated person decides from the estimator's view

    def __post_init__(self) -> None:
        if self.policy != "vla" and (self.perception or self.operator_sees):
            raise SettingError("perception", "serves the vla policy (the state policy reads poses)")
        if self.success_frames != 1 and not self.classifier_episodes:
            raise SettingError("success_frames", "is the classifier's: give `classifier_episodes`")
        if self.operator_sees and not self.perception:
            raise SettingError(
                "operator_sees", "is the pose estimator's view: give `perception` episodes"
            )

    def privileged_reads(self) -> list[str]:
        """What of the run reads state only the plant knows (none: a real cell's run)."""
        reads = {
            "the policy reads the true object poses": self.policy == "state",
            "success is the plant's truth": not self.classifier_episodes,
            "the simulated person judges from the plant's progress": not self.operator_sees,
        }
        return [what for what, read in reads.items() if read]

    @property
    def privileged(self) -> bool:
        """Whether anything of the run reads state only the plant knows."""
        return bool(self.privileged_reads())


_QUICK = Preset(
    policy="state",
    # Objects seen from the TCP: better at every stage (docs/results/defaults.md).
    inputs="relative",
    real_demos=30,
    # More twin demos made a better SFT policy (docs/results/defaults.md).
    twin_id=105,
    twin_ood=105,
    # Twin RL is where RL is cheap: more steps kept climbing (docs/results/defaults.md).
    twin_rl_steps=9600,
    twin_envs=8,
    mining_grid=(4, 4),
    mining_episodes=2,
    plant_steps=2400,
    # 32 episodes per region, every 2 plant minutes (docs/results/defaults.md).
    eval_every=1200,
    eval_grid=(8, 8),
    eval_episodes=1,
    offline_steps=200,
    refresh_every=8,
    seeds=(0, 1, 2),
)


PRESETS = {
    # A few minutes: checks that every stage runs (no learning to speak of).
    "smoke": Preset(
        policy="state",
        real_demos=2,
        twin_id=2,
        twin_ood=2,
        twin_rl_steps=40,
        twin_envs=2,
        mining_grid=(2, 2),
        mining_episodes=1,
        plant_steps=100,
        eval_every=50,
        eval_grid=(2, 2),
        eval_episodes=1,
        offline_steps=5,
        refresh_every=1,
        seeds=(0,),
        sft_steps=30,
    ),
    "quick": _QUICK,
    # Nothing privileged: the image policy through a pose estimator trained on twin
    # renders, success from a classifier trained on twin episodes, the simulated person
    # judging from the estimator's view; real RL as in quick, one seed
    # (docs/results/pipeline-quick.md#nothing-privileged-the-quick-vision-preset).
    "quick-vision": replace(
        _QUICK,
        policy="vla",
        inputs="absolute",
        # Table I's best image row (docs/results/image-policy.md).
        twin_id=30,
        twin_ood=60,
        twin_rl_steps=2400,
        mining_episodes=1,
        seeds=(0,),
        fit_look=True,
        perception=100,
        classifier_episodes=20,
        # A lone false positive does not end an episode: on the policy's own failed
        # episodes 23 % against 28 % called a success (docs/results/reward-classifier.md).
        success_frames=3,
        operator_sees=True,
    ),
    "paper": Preset(
        policy="vla",
        real_demos=30,
        twin_id=60,
        twin_ood=30,
        twin_rl_steps=20000,
        twin_envs=8,
        mining_grid=(8, 8),
        mining_episodes=2,
        plant_steps=18000,
        eval_every=1200,
        eval_grid=(8, 8),  # 32 episodes per region, as in quick
        eval_episodes=1,
        offline_steps=1000,
        refresh_every=10,
        seeds=(0, 1, 2),
    ),
}


@dataclass(frozen=True)
class Method:
    """How one compared method runs real RL."""

    name: str
    slug: str
    rl_method: str
    from_twin: bool  # start from Stage II (else from the real-only SFT policy)
    twin_buffer: bool
    mined_resets: bool


METHOD_TABLE = (
    Method("TwinRL", "twinrl", "twinrl", True, True, True),
    Method("TwinRL w/o twin buffer", "twinrl_no_buffer", "twinrl", True, False, True),
    Method("ConRFT-style", "conrft", "conrft", False, False, False),
    Method("HiL-SERL", "hil_serl", "hil-serl", False, False, False),
)


def twin_rl_config(p: Preset) -> RLConfig:
    """The RL settings of a preset's Stage II."""
    return RLConfig.for_method("twinrl", offline_steps=p.offline_steps)


def real_rl_config(method: Method, p: Preset, seed: int) -> RLConfig:
    """The RL settings of one real-RL run: the method's, with the preset's offline phase
    (HiL-SERL's warms its critic only: RLConfig.for_method)."""
    return RLConfig.for_method(method.rl_method, seed=seed, offline_steps=p.offline_steps)
