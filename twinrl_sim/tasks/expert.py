"""Scripted experts: privileged-state waypoint followers that emit contract actions.

An expert is a list of :class:`Phase` objects (approach, grasp, lift, transport, place,
release, ...). Each phase computes its TCP goal (position and tool yaw) from the
observation when it starts, then the expert moves the TCP toward it at a bounded speed
and switches phase once the goal is reached and held. Actions follow the episode
contract: ``[dx, dy, dz, rx, ry, rz, gripper]`` in the base frame.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from twinrl_data.schema import GRIPPER_CLOSED as GRIPPER_CLOSED  # the contract's
from twinrl_sim.build import yaw_quat
from twinrl_sim.control import TRACKED_ROTATION, quat_conj, quat_mul, quat_to_rotvec, rotvec_to_quat
from twinrl_sim.planar import wrap_angle, yaw_of
from twinrl_sim.spec import SceneSpec

DOWN = np.array([0.0, 1.0, 0.0, 0.0])  # tool z pointing at the table, tool x along base x
# How far (m) below the approach pose an arm must be for a take-over to correct it
# straight to the grasp rather than back it off to the approach pose.
CORRECTION_CLEARANCE = 0.02
# How far (rad) the expert's commanded tool yaw may run ahead of the measured one. The
# arm turns slower while it travels far; a policy sees only the measured pose, so demos
# whose command ran ahead would teach it to stop turning while the tool is still far off.
TURN_LEAD = 0.1
FINGERS_STILL = 5e-4  # m per control step: fingers moving less than this have stopped


def tool_quat(yaw: float) -> np.ndarray:
    """Orientation of a top-down tool turned by ``yaw`` about the vertical."""
    return quat_mul(yaw_quat(yaw), DOWN)


def nearest_equivalent(angle: float, period: float, reference: float) -> float:
    """The angle ``angle + k * period`` closest to ``reference``."""
    return angle + period * round((reference - angle) / period)


class ObsView:
    """Named access to the contract's observation vectors for a given scene."""

    def __init__(self, scene: SceneSpec, obs: dict[str, np.ndarray]) -> None:
        state = np.asarray(obs["observation.state"], float)
        n = (len(state) - 8) // 2
        self.q = state[:n]
        self.tcp_pos = state[2 * n : 2 * n + 3]
        self.tcp_quat = state[2 * n + 3 : 2 * n + 7]
        self.opening = float(state[-1])
        self._env = np.asarray(obs["observation.environment_state"], float)
        self._index = {name: i for i, name in enumerate(scene.object_names)}

    @property
    def tool_yaw(self) -> float:
        return yaw_of(self.tcp_quat)

    def pose(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        i = 7 * self._index[name]
        return self._env[i : i + 3], self._env[i + 3 : i + 7]

    def position(self, name: str) -> np.ndarray:
        return self.pose(name)[0]

    def yaw(self, name: str) -> float:
        return yaw_of(self.pose(name)[1])


Goal = Callable[[ObsView, dict], tuple[np.ndarray, float]]
"""``goal(view, memory) -> (tcp position (m), tool yaw (rad))`` for a phase."""


AIMING = ("approach", "descend")  # the phases that head for the grasp, open-handed


@dataclass
class Phase:
    """One segment of a scripted motion."""

    name: str
    goal: Goal
    gripper: float
    speed: float = 0.04  # m per control step
    tolerance: float = 0.004  # m
    settle: int = 0  # steps to hold at the goal (e.g. while the gripper closes)
    timeout: int = 60
    wait_gripper: bool = False  # also wait until the fingers stop moving
    on_exit: Callable[[ObsView, dict], None] | None = None


@dataclass
class ScriptedExpert:
    """Runs phases in order; ``act(obs)`` returns the next 7-D action.

    The expert integrates its own reference pose (what it has commanded so far) and
    steps that reference toward each goal, so servo lag never winds the command up;
    a phase ends when the *measured* TCP has arrived and held.
    """

    scene: SceneSpec
    phases: list[Phase]
    memory: dict = field(default_factory=dict)
    phase_index: int = 0
    _goal: tuple[np.ndarray, float] | None = None
    _ref: tuple[np.ndarray, np.ndarray] | None = None
    _steps_in_phase: int = 0
    _held: int = 0
    _last_opening: float = float("nan")

    @property
    def done(self) -> bool:
        return self.phase_index >= len(self.phases)

    @property
    def phase(self) -> str:
        return "done" if self.done else self.phases[self.phase_index].name

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        view = ObsView(self.scene, obs)
        fingers_moving = not abs(view.opening - self._last_opening) < FINGERS_STILL
        self._last_opening = view.opening
        return self._act(view, fingers_moving)

    def _act(self, view: ObsView, fingers_moving: bool) -> np.ndarray:
        if self._ref is None:
            self._ref = (view.tcp_pos.copy(), view.tcp_quat.copy())
        if self.done:
            return np.array([0, 0, 0, 0, 0, 0, self.phases[-1].gripper], dtype=np.float32)
        phase = self.phases[self.phase_index]
        if self._goal is None:
            self._goal = phase.goal(view, self.memory)
            self._steps_in_phase = self._held = 0
        goal_pos, goal_yaw = self._goal
        goal_quat = tool_quat(goal_yaw)
        measured_rot = quat_to_rotvec(quat_mul(goal_quat, quat_conj(view.tcp_quat)))
        reached = (
            float(np.linalg.norm(goal_pos - view.tcp_pos)) < phase.tolerance
            and float(np.linalg.norm(measured_rot)) < 0.03
            and not (phase.wait_gripper and fingers_moving)
        )
        self._steps_in_phase += 1
        if reached:
            self._held += 1
        if (reached and self._held > phase.settle) or self._steps_in_phase > phase.timeout:
            if phase.on_exit is not None:
                phase.on_exit(view, self.memory)
            self.phase_index += 1
            self._goal = None
            return self._act(view, fingers_moving)
        ref_pos, ref_quat = self._ref
        error = goal_pos - ref_pos
        distance = float(np.linalg.norm(error))
        step = error if distance <= phase.speed else error * (phase.speed / distance)
        rot = quat_to_rotvec(quat_mul(goal_quat, quat_conj(ref_quat)))
        angle = float(np.linalg.norm(rot))
        limit = TRACKED_ROTATION  # rad per control step: what the wrist follows
        lead = wrap_angle(yaw_of(ref_quat) - view.tool_yaw)
        if rot[2] * lead > 0:  # turning further ahead of the arm
            limit = min(limit, max(0.0, TURN_LEAD - abs(lead)))
        if angle > limit:
            rot = rot * (limit / angle)
        new_quat = quat_mul(rotvec_to_quat(rot), ref_quat)
        self._ref = (ref_pos + step, new_quat / np.linalg.norm(new_quat))
        return np.concatenate([step, rot, [phase.gripper]]).astype(np.float32)

    def take_over(
        self, obs: dict[str, np.ndarray], holding: str | None = None, correct_within: float = 0.0
    ) -> None:
        """Start acting from the arm's measured state, as an operator taking the
        controls in the middle of an episode: the reference restarts at the measured
        pose. With ``holding`` (the object already lifted in the gripper) the plan
        resumes at the lift. Otherwise it starts from its first phase, except that an
        arm already below the approach pose and within ``correct_within`` m (across the
        table) of the grasp is corrected straight to the grasp (the plan resumes at its
        descent, gripper open) instead of backing off to the approach pose."""
        view = ObsView(self.scene, obs)
        self.memory.clear()
        self._goal, self._ref, self._last_opening = None, None, float("nan")
        self._steps_in_phase = self._held = 0
        self.phase_index = 0
        names = [phase.name for phase in self.phases]
        if holding is not None and "lift" in names:
            self.memory["object_name"] = holding
            self.memory["grasp"] = (view.tcp_pos.copy(), view.tool_yaw)
            remember_grasp(holding)(view, self.memory)
            self.phase_index = names.index("lift")
        elif correct_within > 0 and names[:2] == ["approach", "descend"]:
            self._goal = self.phases[0].goal(view, self.memory)  # samples the grasp
            grasp_pos = self.memory["grasp"][0]
            below = view.tcp_pos[2] < self._goal[0][2] - CORRECTION_CLEARANCE
            across = float(np.linalg.norm((grasp_pos - view.tcp_pos)[:2]))
            if below and across < correct_within:
                self._goal, self.phase_index = None, 1

    def planned_grasp(self, obs: dict[str, np.ndarray]) -> tuple[np.ndarray, float] | None:
        """Where this plan would grasp from ``obs``: (TCP position (m), tool yaw (rad)),
        or ``None`` for a plan without a grasp. Leaves the expert's own state alone."""
        view, memory = ObsView(self.scene, obs), {}
        for phase in self.phases:
            phase.goal(view, memory)
            if "grasp" in memory:
                return memory["grasp"]
        return None

    def reaim(self, offset: np.ndarray) -> bool:
        """Move the grasp it is heading for by ``offset`` (m), with the goal it steps
        toward, while it approaches or descends to it: an operator's aim follows the object
        as they see it better on the way. Returns whether it moved (not before the grasp
        is chosen, nor once the fingers close)."""
        if self.phase not in AIMING or "grasp" not in self.memory or self._goal is None:
            return False
        offset = np.asarray(offset, float)
        position, yaw = self.memory["grasp"]
        self.memory["grasp"] = (position + offset, yaw)
        self._goal = (self._goal[0] + offset, self._goal[1])
        return True

    def perturb(self, translation: np.ndarray, rotation: np.ndarray) -> None:
        """Shift the reference by what was executed on top of the last action (an
        operator's unsteady hand), so the following actions correct it instead of
        leaving the arm off by a random walk."""
        if self._ref is None:
            return
        ref_pos, ref_quat = self._ref
        quat = quat_mul(rotvec_to_quat(np.asarray(rotation, float)), ref_quat)
        self._ref = (ref_pos + np.asarray(translation, float), quat / np.linalg.norm(quat))


# ---------------------------------------------------------------- building blocks
def stopping_short(expert: ScriptedExpert, phase: str, fraction: float) -> ScriptedExpert:
    """A near miss of ``expert``: it goes ``fraction`` of the way from where it enters
    the phase named ``phase`` to that phase's goal, then holds still with the gripper as
    that phase has it. What a reward classifier must not take for a success: an object
    held over its goal, a peg above its hole, a board wiped in part."""
    names = [p.name for p in expert.phases]
    if phase not in names:
        raise ValueError(f"the expert has no phase '{phase}'; its phases: {', '.join(names)}")
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f"a near miss stops a fraction in [0, 1) of the way, got {fraction}")
    k = names.index(phase)
    whole = expert.phases[k].goal

    def short_of_goal(view: ObsView, memory: dict) -> tuple[np.ndarray, float]:
        pos, yaw = whole(view, memory)
        return view.tcp_pos + fraction * (pos - view.tcp_pos), yaw

    last = replace(expert.phases[k], goal=short_of_goal, on_exit=None)
    return replace(expert, phases=[*expert.phases[:k], last])


def grasp_yaw(object_yaw: float, period: float, offset: float, reference: float) -> float:
    """Tool yaw for a grasp ``offset`` from the object's heading, nearest to ``reference``
    among the object's symmetric equivalents (``period``)."""
    return nearest_equivalent(object_yaw + offset, period, reference)


def remember_grasp(object_name: str) -> Callable[[ObsView, dict], None]:
    """``on_exit`` hook storing how the object sits in the closed gripper."""

    def hook(view: ObsView, memory: dict) -> None:
        memory["grasp_offset"] = view.position(object_name) - view.tcp_pos
        memory["grasp_tool_yaw"] = view.tool_yaw
        memory["grasp_rel_yaw"] = view.yaw(object_name) - view.tool_yaw

    return hook


def place_goal(
    object_position: np.ndarray, object_yaw: float, memory: dict
) -> tuple[np.ndarray, float]:
    """TCP pose that puts the grasped object at ``object_position`` with ``object_yaw``."""
    tool_yaw = object_yaw - memory["grasp_rel_yaw"]
    turn = tool_yaw - memory["grasp_tool_yaw"]
    c, s = math.cos(turn), math.sin(turn)
    offset = memory["grasp_offset"]
    rotated = np.array([c * offset[0] - s * offset[1], s * offset[0] + c * offset[1], offset[2]])
    return np.asarray(object_position, float) - rotated, tool_yaw


def sample_grasps(
    rng: np.random.Generator,
    object_yaw: float,
    period: float,
    yaw_offset: float,
    along_axis: float,
    reference_yaw: float,
    count: int = 16,
) -> list[tuple[float, float]]:
    """Candidate top-down grasps ``(tool yaw, shift along the object's x axis)`` ranked
    best first: small wrist rotation from ``reference_yaw``, then central grasps."""
    candidates = []
    for _ in range(count):
        nominal = grasp_yaw(object_yaw, period, yaw_offset, reference_yaw)
        shift = rng.uniform(-along_axis, along_axis)
        cost = abs(nominal - reference_yaw) + 2.0 * abs(shift)
        # The yaw jitter is drawn after ranking so that ranking does not bias it.
        candidates.append((cost, nominal, shift))
    candidates.sort()
    return [(yaw + rng.normal(0.0, 0.02), shift) for _, yaw, shift in candidates]


GraspChooser = Callable[[ObsView], tuple[np.ndarray, float]]
"""``choose(view) -> (TCP grasp position (m), tool yaw (rad))``."""
PlacementChooser = Callable[[ObsView, dict], tuple[np.ndarray, float]]
"""``choose(view, memory) -> (final object position (m), final object yaw (rad))``."""


def pick_phases(
    object_name: str,
    choose_grasp: GraspChooser,
    *,
    approach_height: float = 0.10,
    lift_height: float = 0.16,
    close_steps: int = 1,
) -> list[Phase]:
    """Approach above a sampled grasp, descend, close, remember the grasp, lift."""

    def approach(view: ObsView, memory: dict) -> tuple[np.ndarray, float]:
        memory["object_name"] = object_name
        memory["grasp"] = choose_grasp(view)
        pos, yaw = memory["grasp"]
        return pos + [0.0, 0.0, approach_height], yaw

    def at_grasp(view: ObsView, memory: dict) -> tuple[np.ndarray, float]:
        return memory["grasp"]

    def lift(view: ObsView, memory: dict) -> tuple[np.ndarray, float]:
        pos, yaw = memory["grasp"]
        return np.array([pos[0], pos[1], lift_height]), yaw

    return [
        Phase("approach", approach, gripper=0.0, tolerance=0.005),
        Phase("descend", at_grasp, gripper=0.0, speed=0.015),
        Phase(
            "close",
            at_grasp,
            gripper=1.0,
            settle=close_steps,
            tolerance=0.01,
            wait_gripper=True,
            on_exit=remember_grasp(object_name),
        ),
        Phase("lift", lift, gripper=1.0, tolerance=0.01),
    ]


def place_phases(
    choose_placement: PlacementChooser,
    *,
    hover_height: float = 0.07,
    hover_tolerance: float = 0.005,
    final_speed: float = 0.01,
    release_steps: int = 1,
    retreat_height: float = 0.10,
) -> list[Phase]:
    """Carry above the placement, lower slowly, release and retreat straight up."""

    def placed(view: ObsView, memory: dict) -> tuple[np.ndarray, float]:
        if "placement" not in memory:
            memory["placement"] = place_goal(*choose_placement(view, memory), memory)
        return memory["placement"]

    def regrasp(view: ObsView, memory: dict) -> None:
        """Re-measure how the object hangs in the gripper and re-aim the placement."""
        object_name = memory["object_name"]
        remember_grasp(object_name)(view, memory)
        memory.pop("placement", None)

    def hover(view: ObsView, memory: dict) -> tuple[np.ndarray, float]:
        pos, yaw = placed(view, memory)
        return pos + [0.0, 0.0, hover_height], yaw

    def retreat(view: ObsView, memory: dict) -> tuple[np.ndarray, float]:
        pos, yaw = placed(view, memory)
        return pos + [0.0, 0.0, retreat_height], yaw

    return [
        Phase("transport", hover, gripper=1.0, tolerance=0.01, on_exit=regrasp),
        Phase("align", hover, gripper=1.0, tolerance=hover_tolerance, settle=1, on_exit=regrasp),
        Phase("lower", placed, gripper=1.0, speed=final_speed, tolerance=0.003, timeout=40),
        Phase(
            "release", placed, gripper=0.0, settle=release_steps, tolerance=0.02, wait_gripper=True
        ),
        Phase("retreat", retreat, gripper=0.0, tolerance=0.01),
    ]
