"""The studies' settings records, light to import: the command line derives its
options from them without loading torch or the simulator."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from twinrl_data.errors import SettingError
from twinrl_data.executor import cluster_address
from twinrl_learn.compute import check_device
from twinrl_learn.settings import check_inputs

STAGE1_POLICIES = ("state", "vla", "act")


@dataclass
class Stage1Settings:
    """What ``twinrl bench stage1`` runs: each field is also its option and help."""

    tasks: tuple[str, ...] = ("pick_place", "insert_hexagon")
    """Tasks to run (repeatable)."""
    policies: tuple[str, ...] = ("state",)
    """Policy kinds to train: state, vla, act (lerobot's ACT by lerobot's trainer, on the
    same episodes without the object poses; meant for a GPU) (repeatable)."""
    real: int = 30
    """Real (plant) demonstrations in the ID region."""
    scale: float = 1.0
    """Multiplies every demo count (0.1 for a smoke run)."""
    grid: tuple[int, int] = (4, 4)
    """Evaluation grid over ID and OOD, e.g. 4x4."""
    episodes_per_cell: int = 4
    """Evaluation episodes per grid cell."""
    vla_steps: int | None = None
    """SFT steps of the image policy (default: its own)."""
    state_steps: int | None = None
    """SFT steps of the state policy (default: its own)."""
    act_steps: int = 3000
    """Training steps of lerobot's ACT (batch 16; about 5 s each on 2 CPU cores, 60 ms
    on one H200 GPU)."""
    fit_look: bool = False
    """Fit the twin's appearance (light, table colour) to the real demos' images (gap
    diagnose) and synthesize the twin demos in that look."""
    detours: float = 0.0
    """Share of the twin demos that first stray beside the object (see expand)."""
    perception: int = 0
    """Twin episodes per region (synthesized in the twin of the demos, half of them
    straying first, under varied light) that a pose estimator learns from; the image
    policy then acts through it (`twinrl train perception`). 0: the image policy's own
    encoders, trained with it."""
    state_inputs: str = "relative"
    """The state policy's inputs: relative (objects seen from the TCP, the quick
    pipeline's: with absolute poses the best mix varied) or absolute (poses in the base
    frame)."""
    seed: int = 0
    """Seed for demos, SFT and evaluation."""
    device: str = "auto"
    """Where the networks run: auto (a GPU if torch sees one), cpu, cuda or cuda:N."""

    def __post_init__(self) -> None:
        check_device(self.device)
        check_inputs(self.state_inputs, "state")
        if self.episodes_per_cell < 1:
            raise SettingError(
                "episodes_per_cell", f"must be at least 1, got {self.episodes_per_cell}"
            )
        unknown = sorted(set(self.policies) - set(STAGE1_POLICIES))
        if unknown:
            raise SettingError(
                "policies", f"has {', '.join(unknown)}; use {', '.join(STAGE1_POLICIES)}"
            )
        if self.act_steps < 1:
            raise SettingError("act_steps", f"must be at least 1, got {self.act_steps}")
        if self.perception < 0:
            raise SettingError("perception", f"must be >= 0, got {self.perception}")
        if not 0.0 <= self.detours <= 1.0:
            raise SettingError("detours", f"is a share from 0 to 1, got {self.detours}")

    @property
    def needs_images(self) -> bool:
        """Whether a policy to train reads the cameras (the twin demos then render them)."""
        return bool({"vla", "act"} & set(self.policies))

    def sft_steps(self, kind: str) -> int | None:
        """The SFT steps asked for policies of ``kind`` (None: the kind's own)."""
        return {"vla": self.vla_steps, "state": self.state_steps}.get(kind)


@dataclass(frozen=True)
class StagesSettings:
    """What ``twinrl bench stages`` measures: each field is also its option and help."""

    run: Path
    """A `twinrl demo` run folder (Stage II done)."""
    out: Path
    """Folder for stages.md, stages.json, stages.png."""
    seeds: tuple[int, ...] = (0, 1, 2, 3, 4)
    """Seeds: one evaluation and offline phase each (comma-separated)."""
    grid: tuple[int, int] = (8, 8)
    """Evaluation grid over ID and OOD, e.g. 8x8."""
    episodes: int = 2
    """Evaluation episodes per grid cell."""
    finals: bool = True
    """Also measure the final policies of the run's TwinRL runs."""
    workers: int | None = None
    """Evaluations side by side (default: one at a time; on a cluster, one per CPU)."""
    cluster: str = ""
    """Where the evaluations run: none (this machine's worker processes), local, auto,
    HOST:PORT or ray://HOST:PORT (a Ray cluster's head); see docs/guides/scale-out.md."""

    def __post_init__(self) -> None:
        if self.episodes < 1:
            raise SettingError("episodes", f"must be at least 1, got {self.episodes}")
        if not self.seeds:
            raise SettingError("seeds", "needs at least one seed")
        if self.workers is not None and self.workers < 1:
            raise SettingError("workers", f"must be at least 1, got {self.workers}")
        cluster_address(self.cluster)  # a bad address stops here, before anything runs
