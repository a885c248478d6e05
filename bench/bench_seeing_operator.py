"""How far an operator who sees (:class:`~twinrl_learn.seeing_operator.SeeingOperator`)
judges from the plant: on recorded plant episodes, each frame's objects placed by the
pose estimator against their logged poses (planar error per object and region), and the
progress and success it judges against the same operator given exact poses (the
relative poses a perfect estimator would say). Usage::

    python bench/bench_seeing_operator.py ESTIMATOR SESSION --task pick_place
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import numpy as np
import torch
import typer

from twinrl_data.schema import ENVIRONMENT_STATE, STATE, Episode, image_field
from twinrl_data.sources import discover_episodes
from twinrl_learn.perception.estimator import PoseEstimator
from twinrl_learn.policy.inputs import relative_poses
from twinrl_learn.seeing_operator import SeeingOperator
from twinrl_sim.tasks import TaskConfig, make_task


class _Exact:
    """A perfect estimator for one episode: its logged poses, as an estimator says them."""

    def __init__(self, estimator: PoseEstimator, episode: Episode, names: list[str]) -> None:
        self.config, self.row = estimator.config, 0
        state = torch.as_tensor(episode.data[STATE])
        environment = torch.as_tensor(episode.data[ENVIRONMENT_STATE])
        tcp = episode.meta.names[STATE].index("tcp.x")
        indices = [7 * names.index(n) for n in estimator.config.objects]
        self.rows = relative_poses(state, environment, tcp, indices, True)

    def estimate(self, images, state) -> torch.Tensor:
        return self.rows[self.row][None]


def main(
    estimator: Annotated[Path, typer.Argument(help="Pose estimator folder.")],
    session: Annotated[Path, typer.Argument(help="Recorded plant episodes (session, dataset).")],
    task: Annotated[str, typer.Option(help="Task whose episodes are judged.")] = "pick_place",
) -> None:
    seeing_estimator = PoseEstimator.from_pretrained(estimator)
    the_task = make_task(task)
    names = the_task.scene.object_names
    seeing = SeeingOperator(seeing_estimator, seed=0)
    exact = SeeingOperator(seeing_estimator, seed=0)
    differences, truth, seen, errors, regions = [], [], [], [], []
    episodes = [e for e in discover_episodes([session], images=True) if e.meta.task == task]
    for episode in episodes:
        exact.estimator = perfect = _Exact(seeing_estimator, episode, names)
        config = TaskConfig.from_dict(episode.meta.config)
        seeing.reset(the_task, config)
        exact.reset(the_task, config)
        for t in range(len(episode)):
            perfect.row = t
            observation = {
                STATE: episode.data[STATE][t],
                **{image_field(c): episode.images[c][t] for c in seeing.cameras},
            }
            seen_obs, seen_progress = seeing.seen(observation)
            _, exact_progress = exact.seen(observation)
            differences.append(
                abs(sum(seen_progress.terms.values()) - sum(exact_progress.terms.values()))
            )
            truth.append(exact_progress.success)
            seen.append(seen_progress.success)
            offset = seen_obs[ENVIRONMENT_STATE] - episode.data[ENVIRONMENT_STATE][t]
            errors.append(np.linalg.norm(offset.reshape(-1, 7)[:, :2], axis=1))
            regions.append(episode.meta.region)
    truth_, seen_ = np.array(truth), np.array(seen)
    errors_, regions_ = 100 * np.array(errors, np.float64), np.array(regions)
    hits = int((truth_ & seen_).sum())
    report = {
        "episodes": len(episodes),
        "frames": len(truth_),
        "objects": names,
        "planar error, median cm, by region": {
            r: np.median(errors_[regions_ == r], axis=0).round(2).tolist()
            for r in sorted(set(regions))
        },
        "progress difference, mean": float(np.mean(differences)),
        "progress difference, 90th percentile": float(np.percentile(differences, 90)),
        "success frames": int(truth_.sum()),
        "success precision": hits / max(int(seen_.sum()), 1),
        "success recall": hits / max(int(truth_.sum()), 1),
    }
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    typer.run(main)
