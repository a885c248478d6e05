"""Forward replay with multiple shooting, row-aligned for localisation.

A single replay of a long episode lets a small early error (a slightly different
friction) accumulate until everything disagrees; restarting every ``window`` steps from
what was measured keeps each comparison local, so that the residuals say which effect
acts where. The windows and their replay are identification's own
(:mod:`twinrl_sim.gap.windows`, :mod:`twinrl_sim.windowed`), laid back along the
episode's rows. When the episode logs joint torques, the replay also carries the
inverse dynamics comparison (``tau_id.*``, see :mod:`twinrl_sim.gap.inverse`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from mujoco.rollout import Rollout

from twinrl_data import schema as contract
from twinrl_sim.build import compile_scene
from twinrl_sim.gap.inverse import inverse_dynamics, inverse_model
from twinrl_sim.gap.windows import cut_windows, measured_starts, replay_signals
from twinrl_sim.spec import SceneSpec
from twinrl_sim.windowed import WindowedReplay


@dataclass(frozen=True)
class ShootingReplay:
    """Measured and replayed signals of one episode's compared rows (every row but the
    first), row-aligned (T rows).

    Row ``t`` of ``predicted`` is what the twin gave ``step_in_window[t]`` control
    steps after the start of the window that compares it.
    """

    names: list[str]  # q.*, qd.*, tcp.x/y/z, [tau.*], [<object>.x/y/z], then tau_id.*
    measured: np.ndarray  # (T, n)
    predicted: np.ndarray  # (T, n)
    window: np.ndarray  # (T,) index of the shooting window of each row
    step_in_window: np.ndarray  # (T,) 1..window
    targets: np.ndarray  # (T, n_arm) joint targets sent at each row
    gripper: np.ndarray  # (T,) gripper command at each row
    fps: float

    def columns(self, prefix: str) -> list[int]:
        return [i for i, n in enumerate(self.names) if n.startswith(prefix)]


def replay_windows(
    episode: contract.Episode,
    scene: SceneSpec,
    *,
    effects: dict | None = None,
    window: int | None = None,
) -> ShootingReplay:
    """Replay ``episode`` in the twin built from ``scene`` (plus ``effects``), restarting
    from the measurement every ``window`` steps (default: 2 s of the log, see
    :func:`~twinrl_sim.gap.windows.cut_windows`); the last window ends at the last row."""
    compiled = compile_scene(scene, extra_effects=effects or None)
    objects = [o.name for o in scene.objects]
    windows = cut_windows([episode], compiled.layout, objects, window=window, cover_tail=True)
    with Rollout(nthread=2) as pool:
        engine = WindowedReplay(compiled.layout, windows.fps, pool)
        starts = measured_starts(compiled.model, compiled.layout, windows)
        signals, _ = replay_signals(engine, [compiled.model], windows, starts)
    rows = len(episode.data[contract.STATE])
    measured = np.zeros((rows, len(windows.names)))
    predicted = np.zeros_like(measured)
    owner = np.full(rows, -1)
    step = np.zeros(rows, int)
    for k, start in enumerate(windows.start):
        compared = start + 1 + np.arange(windows.rows)
        fresh = owner[compared] < 0  # the tail window repeats rows already compared
        measured[compared[fresh]] = windows.measured[k][fresh]
        predicted[compared[fresh]] = signals[0, k][fresh]
        step[compared[fresh]] = 1 + np.arange(windows.rows)[fresh]
        owner[compared[fresh]] = k
    kept = owner >= 0
    names = list(windows.names)
    torques = inverse_dynamics(episode, inverse_model(scene, effects))
    if torques is not None:
        names += torques.names
        measured = np.concatenate([measured, torques.measured], axis=1)
        predicted = np.concatenate([predicted, torques.predicted], axis=1)
    actions = episode.data.get(contract.ACTION)
    gripper = np.zeros(rows) if actions is None else np.clip(actions[:, 6], 0, 1)
    return ShootingReplay(
        names,
        measured[kept],
        predicted[kept],
        owner[kept],
        step[kept],
        episode.data[contract.JOINT_TARGET].astype(float)[kept],
        gripper[kept],
        windows.fps,
    )
