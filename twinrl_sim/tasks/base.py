"""What every task has: configurations, ID/OOD regions, success, reward, instruction.

A configuration is the initial state a task needs to regenerate an episode: the
manipulated object's table pose ``object = (x, y, yaw)`` and the target's ``target =
(x, y, yaw)`` (base frame, metres and radians). As in TwinRL, the regions split the
table by where the manipulated object's centre ends up, i.e. by the target; the object
starts in the same region.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from twinrl_data.schema import EpisodeMeta
from twinrl_sim.build import yaw_quat
from twinrl_sim.cell import Cell
from twinrl_sim.errors import TwinError
from twinrl_sim.spec import SceneSpec, load_spec

if TYPE_CHECKING:
    from twinrl_sim.tasks.expert import ScriptedExpert

SCENES_DIR = Path(__file__).resolve().parent.parent / "scenes"
REGION_NAMES = ("ID", "OOD")


@dataclass(frozen=True)
class Region:
    """An axis-aligned rectangle of the table (base frame, m)."""

    name: str
    x: tuple[float, float]
    y: tuple[float, float]

    def contains(self, x: float, y: float) -> bool:
        return self.x[0] <= x <= self.x[1] and self.y[0] <= y <= self.y[1]

    def sample(self, rng: np.random.Generator) -> np.ndarray:
        return np.array([rng.uniform(*self.x), rng.uniform(*self.y)])


# Default split of the table in front of the robot: ID on the right (y < 0), OOD on
# the left (y > 0), with a gap between them so that the regions are disjoint.
DEFAULT_REGIONS = {
    "ID": Region("ID", x=(0.30, 0.60), y=(-0.40, -0.04)),
    "OOD": Region("OOD", x=(0.30, 0.60), y=(0.04, 0.40)),
}


@dataclass(frozen=True)
class TaskConfig:
    """Initial configuration of an episode: object and target table poses."""

    object: tuple[float, float, float]
    target: tuple[float, float, float]

    def __post_init__(self) -> None:
        for key in ("object", "target"):
            value = getattr(self, key)
            if len(value) != 3 or not all(math.isfinite(float(v)) for v in value):
                raise TwinError(
                    f"config.{key} must be three finite numbers (x m, y m, yaw rad), got {value!r}"
                )
            object.__setattr__(self, key, tuple(float(v) for v in value))

    def to_dict(self) -> dict[str, list[float]]:
        return {"object": list(self.object), "target": list(self.target)}

    @classmethod
    def from_dict(cls, data: Any) -> TaskConfig:
        """Read a logged configuration; the error says which keys are wrong."""
        if isinstance(data, TaskConfig):
            return data
        if not isinstance(data, dict):
            raise TwinError(
                f"a config is a mapping {{object: [x, y, yaw], target: [x, y, yaw]}}, got {data!r}"
            )
        keys = set(data)
        if keys != {"object", "target"}:
            raise TwinError(
                f"config needs exactly the keys object and target (got {sorted(keys)}); "
                "each is [x m, y m, yaw rad]"
            )
        return cls(object=tuple(data["object"]), target=tuple(data["target"]))


@dataclass
class Progress:
    """Task evaluation after a control step."""

    success: bool
    terms: dict[str, float] = field(default_factory=dict)


class Tracker:
    """Per-episode task state (e.g. which marks are wiped); stateless tasks use this one."""

    def __init__(self, task: Task, cell: Cell, config: TaskConfig) -> None:
        self.task, self.cell, self.config = task, cell, config

    def update(self) -> Progress:
        return self.task.evaluate(self.cell, self)


class Task(ABC):
    """Base class of the four tasks. Subclasses set the class attributes and methods."""

    name: ClassVar[str]
    instruction: ClassVar[str]
    object_name: ClassVar[str]
    target_name: ClassVar[str]
    max_steps: ClassVar[int] = 100
    min_separation: ClassVar[float] = 0.15  # object-target centre distance at reset (m)
    object_yaw: ClassVar[tuple[float, float]] = (-math.pi / 2, math.pi / 2)
    target_yaw: ClassVar[tuple[float, float]] = (-0.4, 0.4)
    # Tool yaws that grasp the object alike repeat every grasp_period (the parallel
    # gripper's half turn, or the object's own finer symmetry); the nominal grasp's tool
    # yaw is grasp_yaw_offset from the object's heading. Experts and the planner grasp
    # near it, so that demos of neighbouring configurations turn the wrist the same way.
    grasp_period: ClassVar[float] = math.pi
    grasp_yaw_offset: ClassVar[float] = 0.0
    regions: ClassVar[dict[str, Region]] = DEFAULT_REGIONS
    # A near miss (expert.stopping_short): the expert's phase it stops short in, and the
    # range of the fraction of that phase it goes. Pick and place: lowering the object
    # onto its goal, stopped 4-35 mm above it with the object still held.
    near_miss: ClassVar[tuple[str, float, float]] = ("lower", 0.5, 0.95)
    tracker_class: ClassVar[type[Tracker]] = Tracker

    def __init__(self, scene: SceneSpec | None = None) -> None:
        self.scene = scene if scene is not None else self.default_scene()
        for name in (self.object_name, self.target_name):
            self.scene.object(name)  # raises with the names that exist

    @classmethod
    def default_scene(cls) -> SceneSpec:
        """The built-in scene spec of this task (``twinrl_sim/scenes/<task>.yaml``)."""
        return load_spec(SCENES_DIR / f"{cls.name}.yaml")

    @classmethod
    def default_config(cls) -> dict[str, Any]:
        """Reward settings; ``dense`` weights are keyed like the terms of :meth:`evaluate`."""
        return {
            "success_reward": 10.0,
            "step_penalty": 0.05,
            "dense_weights": {"reach": 1.0, "grasp": 1.0, "place": 2.0},
        }

    # ------------------------------------------------------------ configs
    def sample_config(self, rng: np.random.Generator, region: str | None = None) -> TaskConfig:
        """A random configuration in ``region`` (``ID``/``OOD``; ``None`` = either)."""
        if region is None:
            region = REGION_NAMES[int(rng.integers(len(REGION_NAMES)))]
        area = self.region(region)
        for _ in range(1000):
            target_xy = area.sample(rng)
            object_xy = area.sample(rng)
            if np.linalg.norm(target_xy - object_xy) >= self.min_separation:
                return TaskConfig(
                    object=(*object_xy, rng.uniform(*self.object_yaw)),
                    target=(*target_xy, rng.uniform(*self.target_yaw)),
                )
        raise RuntimeError(f"{self.name}: region {region} is too small for min_separation")

    def region(self, name: str) -> Region:
        if name not in self.regions:
            raise TwinError(f"unknown region '{name}'; choose one of {', '.join(self.regions)}")
        return self.regions[name]

    def region_of(self, config: TaskConfig) -> str | None:
        """``ID``, ``OOD`` or ``None``: where the object's centre ends up (the target)."""
        x, y, _ = config.target
        for name, area in self.regions.items():
            if area.contains(x, y):
                return name
        return None

    # ------------------------------------------------------------ episodes
    def place(self, cell: Cell, config: TaskConfig) -> None:
        """Put the object and the target at their configured table poses."""
        top = cell.table_top
        for name, (x, y, yaw) in (
            (self.object_name, config.object),
            (self.target_name, config.target),
        ):
            height = self.scene.object(name).pos[2]
            cell.place_object(name, np.array([x, y, top + height]), yaw_quat(yaw))

    def start(self, cell: Cell, config: TaskConfig) -> Tracker:
        """Regenerate the initial state of ``config`` in ``cell``; return its tracker."""
        cell.reset_robot()
        self.place(cell, config)
        cell.finish_reset()
        return self.tracker_class(self, cell, config)

    @abstractmethod
    def evaluate(self, cell: Cell, tracker: Tracker) -> Progress:
        """Success and dense shaping terms (each in [0, 1]) of the current state."""

    def reward(
        self, progress: Progress, mode: str, settings: dict[str, Any] | None = None
    ) -> float:
        """Sparse: ``success_reward`` on success minus ``step_penalty`` per step (the
        paper's +10 / -0.05). Dense: the sparse reward plus weighted shaping terms."""
        settings = settings or self.default_config()
        reward = settings["success_reward"] * float(progress.success) - settings["step_penalty"]
        if mode == "dense":
            weights = settings["dense_weights"]
            reward += sum(weights.get(k, 0.0) * v for k, v in progress.terms.items())
        elif mode != "sparse":
            raise TwinError(f"reward mode must be 'sparse' or 'dense', got '{mode}'")
        return reward

    @abstractmethod
    def goal_poses(self, cell: Cell, config: TaskConfig) -> list[tuple[np.ndarray, float]]:
        """Where the manipulated object must go: world positions and yaws of its body,
        in order (one pose to place it; several for a path such as wiping)."""

    @property
    def releases_object(self) -> bool:
        """Whether the object is let go at the last goal pose (placing) or kept (tools)."""
        return True

    @abstractmethod
    def expert(self, config: TaskConfig, rng: np.random.Generator) -> ScriptedExpert:
        """The scripted expert for ``config`` (privileged state, IK, sampled grasps)."""

    def episode_meta(
        self,
        *,
        source: str,
        world: str,
        names: dict[str, list[str]],
        config: TaskConfig | None = None,
        region: str | None = None,
        policy: str | None = None,
        operator: str | None = None,
        instruction: str | None = None,
        randomization: dict[str, Any] | None = None,
    ) -> EpisodeMeta:
        """Metadata of an episode of this task in its cell: what every recorder writes
        (the cell's rate, robot and scene digest come from the scene spec)."""
        return EpisodeMeta(
            task=self.name,
            instruction=self.instruction if instruction is None else instruction,
            source=source,
            world=world,
            region=region,
            config=config.to_dict() if config is not None else {},
            twin=self.scene.digest,
            policy=policy,
            fps=self.scene.physics.control_hz,
            robot=self.scene.robot.builtin or "custom",
            operator=operator,
            names=names,
            randomization=randomization or {},
        )
