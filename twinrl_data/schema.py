"""The episode contract: per-step fields and per-episode metadata.

An episode is metadata plus steps at the control rate. Field names follow LeRobot's
conventions so that an episode maps one-to-one onto a LeRobotDataset. At step ``t`` the
observation is the one the action was chosen from; ``next.*`` describe the result of
that action.

=============================  ==============  ==================================
field                          type            meaning
=============================  ==============  ==================================
observation.state              float32[n]      proprio (names recorded)
observation.environment_state  float32[m]      object poses (privileged; optional)
observation.effort             float32[n]      joint torques, N m (optional)
observation.wrench             float32[6]      TCP force (N) and torque (N m), base frame (optional)
observation.images.<camera>    uint8 HxWx3     camera frames (optional)
action                         float32[7]      executed end-effector delta
action.policy                  float32[7]      what the policy proposed
command.joint_target           float32[6]      joint targets sent to the servos
intervention                   bool            the executed action came from a human
next.reward                    float32
next.done                      bool
next.success                   bool
=============================  ==============  ==================================
"""

from __future__ import annotations

import datetime as dt
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from twinrl_data.errors import DataError

STATE = "observation.state"
ENVIRONMENT_STATE = "observation.environment_state"
EFFORT = "observation.effort"
WRENCH = "observation.wrench"
CONTROLLER_TIME = "observation.controller_time"
CONTROLLER_TARGET = "observation.controller_target"
IMAGES_PREFIX = "observation.images."
ACTION = "action"
ACTION_POLICY = "action.policy"
JOINT_TARGET = "command.joint_target"
INTERVENTION = "intervention"
REWARD = "next.reward"
DONE = "next.done"
SUCCESS = "next.success"

VECTOR_FIELDS = (
    STATE,
    ENVIRONMENT_STATE,
    EFFORT,
    WRENCH,
    CONTROLLER_TIME,
    CONTROLLER_TARGET,
    ACTION,
    ACTION_POLICY,
    JOINT_TARGET,
)
WRENCH_NAMES = ["force.x", "force.y", "force.z", "torque.x", "torque.y", "torque.z"]
# The action's last entry commands the gripper in [0, 1]: at or above this it closes.
GRIPPER_CLOSED = 0.5
GRIPPER_OPENING = "gripper.opening"  # the state entry of the fingers' opening (m)
"""Names of ``observation.wrench``'s entries."""
CONTROLLER_TIME_NAMES = ["controller.t"]
"""Names of ``observation.controller_time``'s entry: seconds since the episode's start,
on the robot controller's own clock."""
# observation.controller_target: the joint targets (rad) the controller's servo was
# tracking when the step was measured (a UR's RTDE target_q, from the same packet as the
# joints), named like action.joint_target: how far the command stream had got.
SCALAR_FIELDS = (INTERVENTION, REWARD, DONE, SUCCESS)
# Every recorder of twinrl writes all fields; data imported from elsewhere may lack
# all but these two, and a missing field stays missing (it is never invented).
REQUIRED_FIELDS = (STATE, ACTION)

SOURCES = (
    "teleop",
    "twin_demo",
    "twin_rl",
    "real_rl",
    "eval",
    "replay",
    "excitation",
    "imported",  # logs recorded outside twinrl (CSV import)
)
WORLDS = ("real", "twin", "plant")
REGIONS = ("ID", "OOD")


def image_field(camera: str) -> str:
    return f"{IMAGES_PREFIX}{camera}"


def now_iso() -> str:
    return dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds")


@dataclass(frozen=True)
class EpisodeMeta:
    """Per-episode metadata (see the module docstring for the step fields).

    ``config`` is the initial configuration (enough for the twin to regenerate the
    initial state); ``twin`` is the digest of the scene spec used; ``names`` maps vector
    fields to the names of their entries; ``randomization`` records the visual domain
    randomisation a synthesized episode was rendered with. ``success`` and ``num_interventions`` are
    filled in when the episode ends, and ``aborted`` says why it ended early (the arm
    stopped, the connection was lost, the run was interrupted); ``None``: it ran its course.
    ``sensors`` says what a real cell's sensors delivered during it (per camera: frames,
    dropped, and stale, the control steps that got no new frame); ``note`` is what the
    person recording it typed about it.
    """

    task: str
    source: str
    world: str
    instruction: str = ""
    region: str | None = None
    config: dict[str, Any] = field(default_factory=dict)
    twin: str | None = None
    policy: str | None = None
    success: bool | None = None
    num_interventions: int = 0
    fps: float = 10.0
    robot: str = "ur5e"
    operator: str | None = None
    names: dict[str, list[str]] = field(default_factory=dict)
    randomization: dict[str, Any] = field(default_factory=dict)
    aborted: str | None = None
    sensors: dict[str, Any] = field(default_factory=dict)
    note: str | None = None
    episode_id: str = field(default_factory=lambda: uuid.uuid4().hex[:12])
    created_at: str = field(default_factory=now_iso)

    def __post_init__(self) -> None:
        problems = []
        if not self.task:
            problems.append("task is empty")
        if self.source not in SOURCES:
            problems.append(f"source '{self.source}' is not one of {', '.join(SOURCES)}")
        if self.world not in WORLDS:
            problems.append(f"world '{self.world}' is not one of {', '.join(WORLDS)}")
        if self.region is not None and self.region not in REGIONS:
            problems.append(f"region '{self.region}' is not ID, OOD or None")
        if not self.fps > 0:
            problems.append(f"fps must be positive, got {self.fps}")
        if problems:
            raise DataError("episode metadata: " + "; ".join(problems))

    def replace(self, **changes: Any) -> EpisodeMeta:
        return replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> EpisodeMeta:
        """Read metadata written by :meth:`to_dict`; unknown keys are an error."""
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(data) - known)
        if unknown:
            raise DataError(
                f"episode metadata has unknown key(s) {unknown}; known: {sorted(known)}"
            )
        return cls(**dict(data))


@dataclass(frozen=True)
class Samples:
    """One sample stream of a live episode, at its source's own rate (a UR controller's
    packages at 500 Hz: :mod:`twinrl_data.streams`)."""

    names: list[str]
    times: np.ndarray  # (n,) s from the episode's start, host clock
    values: np.ndarray  # (n, len(names)) float32
    clock: np.ndarray  # (n,) s, the source's own clock (a controller's timestamp)


@dataclass
class Episode:
    """A whole episode in memory: metadata plus one array per field (T rows).

    ``data`` holds the vector and scalar fields keyed by contract name; ``images`` maps
    camera names to uint8 arrays of shape (T, H, W, 3); ``samples``, when read with
    them, a live episode's sample streams by name (none for an episode of steps only).
    """

    meta: EpisodeMeta
    data: dict[str, np.ndarray]
    images: dict[str, np.ndarray] = field(default_factory=dict)
    samples: dict[str, Samples] = field(default_factory=dict)

    def __post_init__(self) -> None:
        missing = [f for f in REQUIRED_FIELDS if f not in self.data]
        lengths = {k: len(v) for k, v in self.data.items()} | {
            image_field(k): len(v) for k, v in self.images.items()
        }
        problems = []
        if missing:
            problems.append(f"missing field(s) {missing}")
        if len(set(lengths.values())) > 1:
            problems.append(f"fields disagree in length: {lengths}")
        if problems:
            raise DataError(f"episode {self.meta.episode_id}: " + "; ".join(problems))

    def __len__(self) -> int:
        return len(self.data[STATE])

    @property
    def total_reward(self) -> float:
        return float(np.sum(self.data[REWARD]))

    @property
    def cameras(self) -> list[str]:
        return list(self.images)


def effort_names(joints: Sequence[str]) -> list[str]:
    """Names of ``observation.effort``'s entries: the torque (N m) of each named joint."""
    return [f"tau.{j}" for j in joints]


def step_record(
    observation: Mapping[str, Any],
    action: np.ndarray,
    joint_target: np.ndarray,
    reward: float,
    done: bool,
    success: bool,
    *,
    action_policy: np.ndarray | None = None,
    intervention: bool = False,
) -> dict[str, Any]:
    """One step of the contract: the observation the action was chosen from, the action
    (and what the policy proposed, if it differs), the servo targets and the outcome."""
    record = {
        **observation,
        ACTION: action,
        JOINT_TARGET: joint_target,
        INTERVENTION: intervention,
        REWARD: reward,
        DONE: done,
        SUCCESS: success,
    }
    if action_policy is not None:
        record[ACTION_POLICY] = action_policy
    return record


def validate_step(
    step: Mapping[str, Any], expected: Mapping[str, tuple[int, ...]] | None = None
) -> None:
    """Check a step dict against the contract; report every problem in one error.

    ``expected`` maps fields to shapes fixed by the first step of an episode.
    """
    problems = []
    missing = [f for f in REQUIRED_FIELDS if f not in step]
    if missing:
        problems.append(f"missing {missing}")
    known = set(VECTOR_FIELDS) | set(SCALAR_FIELDS)
    extra = [k for k in step if k not in known and not k.startswith(IMAGES_PREFIX)]
    if extra:
        problems.append(
            f"unknown field(s) {extra} (known: {sorted(known)} and {IMAGES_PREFIX}<camera>)"
        )
    for key, value in step.items():
        if key in VECTOR_FIELDS and value is not None:
            shape = np.shape(value)
            if len(shape) != 1:
                problems.append(f"{key} must be a vector, got shape {shape}")
            elif expected and key in expected and shape != expected[key]:
                problems.append(f"{key} has shape {shape}, earlier steps had {expected[key]}")
        elif key.startswith(IMAGES_PREFIX):
            array = np.asarray(value)
            if array.dtype != np.uint8 or array.ndim != 3 or array.shape[2] != 3:
                problems.append(f"{key} must be uint8 HxWx3, got {array.dtype} {array.shape}")
    if problems:
        raise DataError("step does not follow the episode contract: " + "; ".join(problems))
