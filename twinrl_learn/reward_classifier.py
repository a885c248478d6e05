"""A reward classifier: whether the task has succeeded, from the cell's cameras and the
gripper's opening, as HiL-SERL and TwinRL judge success on a real cell (which has no
ground truth).

It learns from recorded episodes. A frame is a success when it shows the task done: in
a successful episode, the frames recorded after the step that succeeded (the loop's
``settle`` steps: ``twinrl record`` keeps them, ``twinrl sim expert --settle`` adds
them; the frame of the succeeding step itself was observed before it). Frames more than
``margin`` steps before that step, and every frame of a failed episode, are not; the
frames in between are left out (the object is being set down: neither).
Episodes are split into fitted and held-out ones (never frames of one episode on both
sides); the held-out accuracy, precision and recall are reported with the held-out
mistakes as images.

    classifier = RewardClassifier.load("runs/success")     # doctest: +SKIP
    classifier.judge(observation)                          # doctest: +SKIP
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from twinrl_data.atomic import write_text_atomic
from twinrl_data.catalog import discover
from twinrl_data.lerobot_io import iter_dataset_episodes
from twinrl_data.mcap_log import read_episode, read_meta
from twinrl_data.schema import STATE, SUCCESS, Episode, image_field
from twinrl_learn.compute import mixed_precision, module_device, resolve_device
from twinrl_learn.errors import LearnError
from twinrl_learn.policy.augmentation import random_shift

WEIGHTS, SETTINGS, METRICS, REPORT, MISTAKES = (
    "weights.safetensors", "classifier.json", "metrics.json", "report.md", "mistakes.png",
)  # fmt: skip


ENCODERS = ("scratch", "pretrained")
ENCODER_WORDS = {
    "scratch": "a CNN trained from scratch",
    "pretrained": "a frozen ImageNet-pretrained encoder with a trained head",
}


@dataclass(frozen=True)
class ClassifierSettings:
    """How the classifier is labelled, shaped and trained."""

    cameras: tuple[str, ...] = ("front",)
    image_size: int = 64  # px, square: each camera is resized to it
    margin: int = 6  # frames before the succeeding step left out as ambiguous
    heldout: float = 0.25  # share of episodes held out
    steps: int = 1500
    batch_size: int = 64
    lr: float = 1e-3
    threshold: float = 0.5
    # scratch: a small CNN trained from scratch on the frames; pretrained: the frozen
    # ImageNet encoder of twinrl_learn.perception with a small trained head (its
    # features of every frame are computed once, so it trains in about the same time)
    encoder: str = "scratch"
    seed: int = 0

    def __post_init__(self) -> None:
        if not self.cameras:
            raise LearnError("the reward classifier needs at least one camera")
        if self.encoder not in ENCODERS:
            raise LearnError(
                f"the reward classifier's `encoder` must be one of {', '.join(ENCODERS)}, "
                f"got '{self.encoder}'"
            )
        if self.margin < 0 or not 0 < self.heldout < 1:
            raise LearnError(
                "the reward classifier's `margin` must be >= 0 and `heldout` in (0, 1)"
            )


@dataclass
class Frames:
    """Labelled frames: images (n, cameras*3, s, s) uint8, gripper opening (n,), label
    (n,) bool, and the episode and step each came from."""

    images: np.ndarray
    gripper: np.ndarray
    labels: np.ndarray
    episode: np.ndarray
    step: np.ndarray

    def take(self, rows: np.ndarray) -> Frames:
        columns = (self.images, self.gripper, self.labels, self.episode, self.step)
        return Frames(*(column[rows] for column in columns))


def _resized(images: np.ndarray, size: int) -> np.ndarray:
    """(n, h, w, 3) uint8 -> (n, 3, size, size) uint8 (area-averaged)."""
    tensor = torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float()
    small = F.interpolate(tensor, size=(size, size), mode="area")
    return small.round().clamp(0, 255).to(torch.uint8).numpy()


def labelled_frames(episodes: Iterable[Episode], settings: ClassifierSettings) -> Frames:
    """Every usable frame of ``episodes`` with its label (see the module docstring)."""
    parts: list[tuple[np.ndarray, ...]] = []
    for index, episode in enumerate(episodes):
        missing = [c for c in settings.cameras if c not in episode.images]
        if missing:
            raise LearnError(
                f"episode {episode.meta.episode_id} has no camera {missing[0]}; it has "
                f"{', '.join(episode.images) or 'none'} (choose `cameras` accordingly)"
            )
        steps = np.arange(len(episode))
        succeeded = np.asarray(episode.data.get(SUCCESS, np.zeros(len(episode), bool)), bool)
        if episode.meta.success and succeeded.any():
            first = int(np.argmax(succeeded))
            positive = steps > first
            keep = positive | (steps < first - settings.margin)
        elif episode.meta.success is False:
            positive, keep = np.zeros(len(episode), bool), np.ones(len(episode), bool)
        else:
            continue  # no outcome recorded: nothing to learn from
        images = np.concatenate(
            [_resized(episode.images[c][keep], settings.image_size) for c in settings.cameras],
            axis=1,
        )
        gripper = np.asarray(episode.data[STATE], np.float32)[keep, -1]
        parts.append((images, gripper, positive[keep], np.full(keep.sum(), index), steps[keep]))
    if not parts:
        raise LearnError("no episode with a recorded outcome (success or failure) to learn from")
    frames = Frames(*(np.concatenate(column) for column in zip(*parts, strict=True)))
    if not frames.labels.any():
        raise LearnError(
            "no frame shows a success: no successful episode goes on after the step that "
            "succeeded; record them with a few `settle` steps after the success (the scripted "
            "expert's; twinrl record keeps them)"
        )
    return frames


class SuccessNet(nn.Module):
    """A small convolutional network over the stacked cameras, with the gripper's opening
    joined before the last layers; one logit."""

    def __init__(self, channels: int, size: int) -> None:
        super().__init__()
        self.features = nn.Sequential(
            nn.Conv2d(channels, 16, 5, stride=2, padding=2), nn.ReLU(),
            nn.Conv2d(16, 32, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(32, 32, 3, stride=2, padding=1), nn.ReLU(),
            nn.AdaptiveAvgPool2d(4), nn.Flatten(),
        )  # fmt: skip
        self.head = nn.Sequential(nn.Linear(32 * 16 + 1, 64), nn.ReLU(), nn.Linear(64, 1))
        self.size = size

    def forward(self, images: torch.Tensor, gripper: torch.Tensor) -> torch.Tensor:
        features = self.features(images.float() / 255.0 - 0.5)
        return self.head(torch.cat([features, gripper[:, None] * 10.0], dim=1))[:, 0]


class PretrainedSuccessNet(nn.Module):
    """Each camera's frozen ImageNet features (:class:`~twinrl_learn.perception.backbone.
    FrozenBackbone`) through a small trained head (keypoints and the maps' mean), joined
    with the gripper's opening; one logit."""

    def __init__(self, cameras: int, size: int) -> None:
        from twinrl_learn.perception.backbone import FrozenBackbone
        from twinrl_learn.perception.estimator import CameraHead

        super().__init__()
        self.heads = nn.ModuleList(CameraHead(keypoints=16, width=64) for _ in range(cameras))
        width = sum(head.out_dim for head in self.heads) + 1
        self.mlp = nn.Sequential(nn.Linear(width, 128), nn.ReLU(), nn.Linear(128, 1))
        self.backbone = FrozenBackbone()
        self.size = size

    def encode(self, images: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Each camera's (fine, coarse) backbone features of stacked uint8 images
        (B, 3 x cameras, S, S)."""
        x = images.float() / 255.0
        return [self.backbone(x[:, 3 * i : 3 * i + 3]) for i in range(len(self.heads))]

    def classify(
        self, features: list[tuple[torch.Tensor, torch.Tensor]], gripper: torch.Tensor
    ) -> torch.Tensor:
        parts = [head(*f) for head, f in zip(self.heads, features, strict=True)]
        return self.mlp(torch.cat([*parts, gripper[:, None] * 10.0], dim=1))[:, 0]

    def forward(self, images: torch.Tensor, gripper: torch.Tensor) -> torch.Tensor:
        return self.classify(self.encode(images), gripper)


def success_net(settings: ClassifierSettings) -> SuccessNet | PretrainedSuccessNet:
    """The network ``settings`` ask for."""
    if settings.encoder == "pretrained":
        return PretrainedSuccessNet(len(settings.cameras), settings.image_size)
    return SuccessNet(3 * len(settings.cameras), settings.image_size)


def _encoded(net: PretrainedSuccessNet, images: np.ndarray) -> list[tuple[torch.Tensor, ...]]:
    """Every frame's backbone features per camera, in half precision, computed once."""
    device = module_device(net)
    with mixed_precision(device):
        return [
            net.backbone.cached(
                torch.from_numpy(images[i : i + 128, 3 * camera : 3 * camera + 3]).to(device)
                .float() / 255.0
                for i in range(0, len(images), 128)
            )
            for camera in range(len(net.heads))
        ]  # fmt: skip


@dataclass(frozen=True)
class ClassifierReport:
    """Held-out scores of a trained classifier."""

    accuracy: float
    balanced_accuracy: float
    precision: float
    recall: float
    heldout_frames: int
    heldout_positives: int
    fitted_frames: int
    fitted_episodes: int
    heldout_episodes: int
    seconds: float


def scores(predicted: np.ndarray, labels: np.ndarray) -> tuple[float, float, float, float]:
    """(accuracy, balanced accuracy, precision, recall) of boolean judgements."""
    tp = float(np.sum(predicted & labels))
    tn = float(np.sum(~predicted & ~labels))
    fp = float(np.sum(predicted & ~labels))
    fn = float(np.sum(~predicted & labels))
    accuracy = (tp + tn) / max(len(labels), 1)
    recall = tp / max(tp + fn, 1.0)
    specificity = tn / max(tn + fp, 1.0)
    precision = tp / max(tp + fp, 1.0)
    return accuracy, (recall + specificity) / 2, precision, recall


def train_reward_classifier(
    episodes: Sequence[Episode],
    out: str | Path,
    settings: ClassifierSettings = ClassifierSettings(),
    progress: Callable[[int, float], None] | None = None,
    device: str = "auto",
) -> ClassifierReport:
    """Train on ``episodes`` (on ``device``: see :mod:`twinrl_learn.compute`), write the
    classifier and its report into ``out``."""
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise LearnError(f"{out} exists and is not empty; choose another `out`")
    started = time.perf_counter()
    tasks = sorted({e.meta.task for e in episodes})
    if len(tasks) > 1:
        raise LearnError(
            f"the episodes are of several tasks ({', '.join(tasks)}); a classifier learns one "
            "task's success: train one per task"
        )
    frames = labelled_frames(episodes, settings)
    rng = np.random.default_rng(settings.seed)
    ids = np.unique(frames.episode)
    held = rng.choice(ids, max(1, round(settings.heldout * len(ids))), replace=False)
    if len(held) == len(ids):
        raise LearnError("too few episodes to hold some out; record more (at least 4)")
    is_held = np.isin(frames.episode, held)
    fitted, heldout = frames.take(~is_held), frames.take(is_held)
    if not fitted.labels.any():
        raise LearnError("the fitted episodes hold no success; record more successful ones")
    on = resolve_device(device)
    torch.manual_seed(settings.seed)
    generator = torch.Generator().manual_seed(settings.seed)
    net = success_net(settings).to(on)
    optimizer = torch.optim.Adam(net.parameters(), lr=settings.lr)
    encoded = _encoded(net, fitted.images) if isinstance(net, PretrainedSuccessNet) else None
    images = None if encoded is not None else torch.from_numpy(fitted.images).to(on)
    gripper = torch.from_numpy(fitted.gripper).to(on)
    labels = torch.from_numpy(fitted.labels.astype(np.float32))
    # Balanced batches: successes are a few frames an episode.
    weights = torch.where(labels > 0, 0.5 / labels.sum(), 0.5 / (1 - labels).sum())
    labels = labels.to(on)
    for step in range(settings.steps):
        rows = torch.multinomial(weights, settings.batch_size, True, generator=generator).to(on)
        with mixed_precision(on):
            if encoded is not None:
                features = [(fine[rows], coarse[rows]) for fine, coarse in encoded]
                logits = net.classify(features, gripper[rows])
            else:
                batch = random_shift(images[rows].float(), generator)  # a camera nudged
                logits = net(batch, gripper[rows])
            loss = F.binary_cross_entropy_with_logits(logits.float(), labels[rows])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        if progress is not None and (step % 50 == 0 or step == settings.steps - 1):
            progress(step + 1, float(loss.detach()))
    net.eval()
    probability = predict(net, heldout.images, heldout.gripper)
    predicted = probability > settings.threshold
    accuracy, balanced, precision, recall = scores(predicted, heldout.labels)
    report = ClassifierReport(
        accuracy=accuracy,
        balanced_accuracy=balanced,
        precision=precision,
        recall=recall,
        heldout_frames=len(heldout.labels),
        heldout_positives=int(heldout.labels.sum()),
        fitted_frames=len(fitted.labels),
        fitted_episodes=len(ids) - len(held),
        heldout_episodes=len(held),
        seconds=time.perf_counter() - started,
    )
    _write(out, net, settings, tasks[0], report, heldout, probability)
    return report


def episodes_under(
    paths: Iterable[str | Path], cameras: Sequence[str], task: str | None = None
) -> list[Episode]:
    """The episodes in ``paths`` (session folders, .mcap files, LeRobot datasets), only
    ``task``'s when given."""
    mcaps, datasets = discover(paths)
    episodes = [read_episode(path) for path in mcaps if task in (None, read_meta(path).task)]
    for root in datasets:
        found = iter_dataset_episodes(root, cameras=list(cameras))
        episodes.extend(e for e in found if task in (None, e.meta.task))
    if not episodes:
        raise LearnError(
            f"no episode{f' of {task}' if task else ''} in {', '.join(map(str, paths))}"
        )
    return episodes


def predict(
    net: SuccessNet | PretrainedSuccessNet, images: np.ndarray, gripper: np.ndarray
) -> np.ndarray:
    """The success probability of each frame (stacked camera images, gripper opening)."""
    device = module_device(net)
    with torch.no_grad(), mixed_precision(device):
        logits = [
            net(
                torch.from_numpy(images[i : i + 256]).to(device),
                torch.from_numpy(gripper[i : i + 256]).to(device),
            ).float()
            for i in range(0, len(images), 256)
        ]
    return torch.sigmoid(torch.cat(logits)).cpu().numpy() if logits else np.zeros(0)


def _write(
    out: Path,
    net: SuccessNet | PretrainedSuccessNet,
    settings: ClassifierSettings,
    task: str,
    report: ClassifierReport,
    heldout: Frames,
    probability: np.ndarray,
) -> None:
    from safetensors.torch import save_file

    out.mkdir(parents=True, exist_ok=True)
    save_file({k: v.contiguous() for k, v in net.state_dict().items()}, str(out / WEIGHTS))
    write_text_atomic(out / SETTINGS, json.dumps({"task": task, **asdict(settings)}, indent=1))
    write_text_atomic(out / METRICS, json.dumps(asdict(report), indent=1))
    wrong = np.flatnonzero((probability > settings.threshold) != heldout.labels)
    _mistakes_png(out / MISTAKES, heldout, probability, wrong[:24])
    write_text_atomic(out / REPORT, _report_md(report, settings, task, len(wrong)))


def _mistakes_png(path: Path, frames: Frames, probability: np.ndarray, rows: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    count = max(len(rows), 1)
    columns = min(count, 6)
    figure, axes = plt.subplots(
        (count + columns - 1) // columns,
        columns,
        figsize=(2.2 * columns, 2.4 * ((count + 5) // 6)),
        squeeze=False,
    )
    for ax in axes.flat:
        ax.axis("off")
    if not len(rows):
        axes[0, 0].text(0.5, 0.5, "no held-out mistakes", ha="center", va="center")
    for ax, row in zip(axes.flat, rows, strict=False):
        ax.imshow(frames.images[row][:3].transpose(1, 2, 0))
        truth = "success" if frames.labels[row] else "not yet"
        ax.set_title(
            f"{truth}, p={probability[row]:.2f}\nep {frames.episode[row]} step {frames.step[row]}",
            fontsize=7,
        )
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def _report_md(
    report: ClassifierReport, settings: ClassifierSettings, task: str, mistakes: int
) -> str:
    r = report
    held = f"{r.heldout_frames} frames ({r.heldout_positives} successes)"
    held += f" of {r.heldout_episodes} episodes"
    scores = f"{r.accuracy:.3f} | {r.balanced_accuracy:.3f} | {r.precision:.3f} | {r.recall:.3f}"
    return "\n".join(
        [
            f"# Reward classifier: {task}",
            "",
            f"Cameras {', '.join(settings.cameras)} at {settings.image_size} px "
            f"({ENCODER_WORDS[settings.encoder]}) and the gripper's opening; the frames "
            "recorded after a successful episode's succeeding step are successes, frames "
            f"more than {settings.margin} steps before it and every frame of a failure are "
            "not.",
            "",
            "| held out | accuracy | balanced accuracy | precision | recall |",
            "|---|---|---|---|---|",
            f"| {held} | {scores} |",
            "",
            f"Fitted on {r.fitted_frames} frames of {r.fitted_episodes} episodes in "
            f"{r.seconds:.0f} s. The held-out mistakes ({mistakes}; at most 24 shown):",
            "",
            f"![mistakes]({MISTAKES})",
            "",
        ]
    )


class RewardClassifier:
    """A trained classifier, to judge success on a cell without ground truth."""

    def __init__(
        self, net: SuccessNet | PretrainedSuccessNet, settings: ClassifierSettings, task: str
    ) -> None:
        self.net, self.settings, self.task = net.eval(), settings, task
        self.threshold = settings.threshold

    @classmethod
    def load(cls, folder: str | Path) -> RewardClassifier:
        from safetensors.torch import load_file

        folder = Path(folder)
        if not (folder / SETTINGS).is_file() or not (folder / WEIGHTS).is_file():
            raise LearnError(
                f"{folder} is not a reward classifier (no {SETTINGS} and {WEIGHTS}); train one "
                "with `twinrl train reward-classifier`"
            )
        try:
            raw = json.loads((folder / SETTINGS).read_text())
            task = raw.pop("task")
            settings = ClassifierSettings(**{**raw, "cameras": tuple(raw["cameras"])})
            net = success_net(settings)
            net.load_state_dict(load_file(str(folder / WEIGHTS)))
        except (ValueError, KeyError, TypeError, RuntimeError) as err:
            reason = str(err).splitlines()[0] if str(err) else type(err).__name__
            raise LearnError(
                f"{folder} holds a reward classifier this version cannot read ({reason}); "
                "train it again with `twinrl train reward-classifier`"
            ) from err
        return cls(net, settings, task)

    def probability(self, observation: dict[str, np.ndarray]) -> float:
        """The probability that ``observation`` shows the task succeeded."""
        missing = [c for c in self.settings.cameras if image_field(c) not in observation]
        if missing:
            raise LearnError(
                f"the reward classifier reads camera {missing[0]}, which this cell does not record"
            )
        images = np.concatenate(
            [
                _resized(observation[image_field(c)][None], self.settings.image_size)
                for c in self.settings.cameras
            ],
            axis=1,
        )
        gripper = np.asarray(observation[STATE], np.float32)[None, -1:]
        return float(predict(self.net, images, gripper[:, 0])[0])

    def judge(self, observation: dict[str, np.ndarray]) -> bool:
        """Whether ``observation`` shows the task done (a :data:`twinrl_robot.loop.Judge`)."""
        return self.probability(observation) > self.threshold

    def episode_judge(self, frames: int = 1) -> Callable[[dict[str, np.ndarray]], bool]:
        """A judge for one episode that calls a success once ``frames`` successive
        observations look like one, so that a lone false positive does not end it (on
        a policy's own failed episodes, 3 frames called 23 % a success against 28 %:
        docs/results/reward-classifier.md)."""
        if frames < 1:
            raise LearnError(f"a success needs at least 1 frame, got {frames}")
        seen = 0

        def judge(observation: dict[str, np.ndarray]) -> bool:
            nonlocal seen
            seen = seen + 1 if self.judge(observation) else 0
            return seen >= frames

        return judge
