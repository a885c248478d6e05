"""A reward classifier judged on episodes it never saw, the way real RL would use it.

Real RL ends an episode once the classifier calls ``success_frames`` successive frames a
success (its ``--success-frames``), so besides the frame scores (labelled as in
:func:`~twinrl_learn.reward_classifier.labelled_frames`) what matters is per episode: a
failed episode with that many successive frames judged a success is a *false success*
(rewarded and ended early), a successful one whose success frames hold no such run is a
*missed success*. Episodes recorded as near misses (the scripted expert stopping short
near the goal: ``twinrl sim expert --near-misses``) are the hard negatives and are
counted apart.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from twinrl_data.atomic import write_text_atomic
from twinrl_data.schema import Episode
from twinrl_learn.errors import LearnError
from twinrl_learn.reward_classifier import RewardClassifier, labelled_frames, predict, scores

NEAR_MISS_POLICY = "scripted_expert:near_miss"  # the policy a near miss is recorded with


@dataclass
class ClassifierCheck:
    """Frame scores and episode outcomes of one classifier on one set of episodes."""

    task: str
    frames: int
    positives: int
    success_frames: int  # successive frames judged a success that make an episode one
    accuracy: float
    balanced_accuracy: float
    precision: float
    recall: float
    successful_episodes: int
    failed_episodes: int
    near_miss_episodes: int  # failed episodes recorded as near misses
    false_successes: int  # failed episodes with a frame judged a success
    near_miss_false_successes: int  # of which near misses
    missed_successes: int  # successful episodes with no success frame judged so

    @property
    def episode_precision(self) -> float:
        """Of the episodes judged successes, the share that succeeded: what real RL's
        rewards are worth."""
        found = self.successful_episodes - self.missed_successes
        return found / max(found + self.false_successes, 1)

    @property
    def episode_recall(self) -> float:
        """Of the successful episodes, the share judged so."""
        return 1.0 - self.missed_successes / max(self.successful_episodes, 1)

    def to_dict(self) -> dict:
        return asdict(self) | {
            "episode_precision": self.episode_precision,
            "episode_recall": self.episode_recall,
        }


def _longest_run(steps: np.ndarray, judged: np.ndarray) -> int:
    """The most successive steps (``steps`` ascending) all judged a success."""
    longest = run = 0
    for i, yes in enumerate(judged):
        run = (run + 1 if i and steps[i] == steps[i - 1] + 1 else 1) if yes else 0
        longest = max(longest, run)
    return longest


def check_reward_classifier(
    classifier: RewardClassifier, episodes: Sequence[Episode], success_frames: int = 1
) -> ClassifierCheck:
    """Judge every labelled frame of ``episodes`` (of the classifier's task) with
    ``classifier``, an episode's success needing ``success_frames`` successive frames
    (see the module docstring)."""
    if success_frames < 1:
        raise LearnError(f"a success needs at least 1 frame, got {success_frames}")
    other = sorted({e.meta.task for e in episodes} - {classifier.task})
    if other:
        raise LearnError(
            f"the classifier judges {classifier.task}, and some episodes are of {other[0]}; "
            "check it on its own task's episodes"
        )
    frames = labelled_frames(episodes, classifier.settings)
    judged = predict(classifier.net, frames.images, frames.gripper) > classifier.threshold
    accuracy, balanced, precision, recall = scores(judged, frames.labels)
    counts = dict.fromkeys(("ok", "failed", "near", "false", "near_false", "missed"), 0)
    for index in np.unique(frames.episode):
        rows = frames.episode == index
        near = episodes[index].meta.policy == NEAR_MISS_POLICY
        if episodes[index].meta.success:
            counts["ok"] += 1
            shown = rows & frames.labels
            seen = _longest_run(frames.step[shown], judged[shown])
            counts["missed"] += bool(shown.any() and seen < success_frames)
        else:
            counts["failed"] += 1
            counts["near"] += near
            wrong = _longest_run(frames.step[rows], judged[rows]) >= success_frames
            counts["false"] += wrong
            counts["near_false"] += wrong and near
    return ClassifierCheck(
        task=classifier.task,
        frames=len(frames.labels),
        positives=int(frames.labels.sum()),
        success_frames=success_frames,
        accuracy=accuracy,
        balanced_accuracy=balanced,
        precision=precision,
        recall=recall,
        successful_episodes=counts["ok"],
        failed_episodes=counts["failed"],
        near_miss_episodes=counts["near"],
        false_successes=counts["false"],
        near_miss_false_successes=counts["near_false"],
        missed_successes=counts["missed"],
    )


def save_check(check: ClassifierCheck, path: str | Path) -> Path:
    """Write ``check`` as JSON to ``path``."""
    path = Path(path)
    write_text_atomic(path, json.dumps(check.to_dict(), indent=1))
    return path
