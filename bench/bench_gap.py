"""Gap diagnosis speed and accuracy: 20 plant excitation episodes of 10 s with hidden
effects, diagnosed against the whole candidate library.

Target: at most 3 minutes on 2 cores. Also measured side by side: one finite-difference
Jacobian of a per-joint candidate (7 parameter points) as one batched ``mujoco.rollout``
call versus one rollout call per parameter point. ``--rate 125`` records and diagnoses
at a UR controller's log rate instead of the 10 Hz control rate, the arm with a UR's
tracking servos. Usage::

    python bench/bench_gap.py --episodes 20 --duration 10
    python bench/bench_gap.py --episodes 20 --duration 10 --rate 125
    python bench/bench_gap.py --episodes 20 --duration 10 --rate 125 --unscreened

``--unscreened`` diagnoses the same log a second time fitting every candidate in every
round (no first-step screen) and prints the time ratio side by side.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_robot.excitation import ExcitationSettings, run_excitation
from twinrl_sim.build import compile_scene
from twinrl_sim.effects import load_effects
from twinrl_sim.gap.diagnose import diagnose
from twinrl_sim.gap.identify import WindowReplay
from twinrl_sim.gap.noise import NoiseFloor
from twinrl_sim.gap.windows import cut_windows
from twinrl_sim.tasks import make_task

TARGET_SECONDS = 180.0
DEFAULT_HIDDEN = {"actuator_delay": {"seconds": 0.03}, "payload": {"mass": 2.0}}


def _jacobian_ratio(scene, episodes) -> tuple[float, float, int]:
    layout = compile_scene(scene).layout
    windows = cut_windows(episodes, layout, scene.object_names)
    windows = windows.subset(np.arange(min(24, len(windows))))
    replay = WindowReplay(scene, windows, NoiseFloor(), free=["joint_friction"])
    x = replay.params.as_vector()
    points = np.column_stack([x] + [x + 1e-3 * np.eye(len(x))[i] for i in range(len(x))])
    start = time.perf_counter()
    replay.residual_fn(points, replay.params.copy())
    batched = time.perf_counter() - start
    start = time.perf_counter()
    for column in points.T:
        replay.residual_fn(column, replay.params.copy())
    one_by_one = time.perf_counter() - start
    return batched, one_by_one, len(windows)


def _shown(value: float | list[float], spec: str) -> str:
    """A number, or a vector as ``a, b, c``."""
    return ", ".join(format(float(v), spec) for v in np.atleast_1d(value))


def main(
    episodes: Annotated[int, typer.Option(help="Excitation episodes recorded.")] = 20,
    duration: Annotated[float, typer.Option(help="Seconds per episode.")] = 10.0,
    effects: Annotated[
        Path | None, typer.Option(help="Hidden effects YAML (default: a delay and a payload).")
    ] = None,
    rate: Annotated[
        float | None,
        typer.Option(help="Log rate (Hz), e.g. 125 as a CB3 logs; default the cell's 10 Hz."),
    ] = None,
    unscreened: Annotated[
        bool,
        typer.Option(help="Also diagnose fitting every candidate in every round (no screen)."),
    ] = False,
) -> None:
    hidden = load_effects(effects) if effects else DEFAULT_HIDDEN
    scene = make_task("pick_place").scene
    if rate is not None:  # a controller's log: its rate, its tracking servos
        physics = scene.physics.model_copy(update={"control_hz": rate, "servo": "track"})
        scene = scene.model_copy(update={"physics": physics})
    session = Session.create(Path(tempfile.mkdtemp(prefix="twinrl-gap-")) / "measured")
    start = time.perf_counter()
    run_excitation(
        "pick_place",
        scene=scene,
        world="plant",
        effects=hidden,
        episodes=episodes,
        settings=ExcitationSettings(duration=duration),
        session=session,
    )
    recording = time.perf_counter() - start
    measured = [read_episode(p, images=False) for p in session.episode_paths()]
    diagnosis = diagnose(measured, scene)
    if unscreened:
        full = diagnose(measured, scene, fitted_per_round=None)
        named = lambda d: ", ".join(s["effect"] for s in d.selected) or "nothing"  # noqa: E731
        print(
            f"unscreened (every candidate fitted): {full.seconds:.1f} s, named {named(full)}, "
            f"held-out {full.gap_before:.3g} -> {full.gap_after:.3g}; screened / unscreened "
            f"time = {diagnosis.seconds / full.seconds:.2f}"
        )
    batched, one_by_one, count = _jacobian_ratio(scene, measured)
    rows = sum(len(e) for e in measured)
    results = [r for rnd in diagnosis.rounds for r in rnd]
    screens = sum(r.screened for r in results)
    print(
        f"recording {episodes} x {duration:g} s at {measured[0].meta.fps:g} Hz ({rows} rows): "
        f"{recording:.1f} s"
    )
    print(
        f"diagnose (whole library, {len(results) - screens} fits, {screens} screened): "
        f"{diagnosis.seconds:.1f} s = {diagnosis.seconds / TARGET_SECONDS:.2f} x the "
        f"{TARGET_SECONDS:.0f} s target"
    )
    print(
        f"FD Jacobian, 7 points x {count} windows: batched {batched:.2f} s, one call per point "
        f"{one_by_one:.2f} s (batched / one by one = {batched / one_by_one:.2f})"
    )
    print("| effect | parameter | hidden | named | 95 % (±) |")
    print("|---|---|---|---|---|")
    for effect, params in hidden.items():
        named = next((s for s in diagnosis.selected if s["effect"] == effect), None)
        for param, truth in params.items():
            fitted = _shown(named["params"][param], ".4g") if named else "not named"
            ci = _shown(named["ci"][param], ".2g") if named else ""
            print(f"| {effect} | {param} | {_shown(truth, 'g')} | {fitted} | {ci} |")
    extra = [s["effect"] for s in diagnosis.selected if s["effect"] not in hidden]
    print(f"named but not hidden: {extra or 'none'}")
    print(
        f"held-out error {diagnosis.gap_before:.3g} -> {diagnosis.gap_after:.3g} "
        f"({100 * diagnosis.heldout_reduction:.1f} % smaller)"
    )
    print("\nwhere the time goes: | round | effect | LM iterations | seconds | screened |")
    for number, results in enumerate(diagnosis.rounds, start=1):
        for r in results:
            screened = "yes" if r.screened else ""
            print(f"| {number} | {r.effect} | {r.iterations} | {r.seconds:.1f} | {screened} |")


if __name__ == "__main__":
    typer.run(main)
