"""Where a pipeline run keeps its stages' data and policies."""

from __future__ import annotations

from pathlib import Path


def stage1_paths(folder: Path, policy: str) -> dict[str, Path]:
    """Where Stage I keeps its data and policies in a run's ``stage1`` folder."""
    return {
        "real": folder / "real",
        "twin": folder / "twin" / "dataset",
        "sft_real": folder / f"{policy}_real",
        "sft_twin": folder / f"{policy}_real_twin",
        "look": folder / "twin_fitted.yaml",  # presets that fit the twin's look
        "estimator": folder / "estimator",  # presets whose image policy sees through one
        "classifier": folder / "success_classifier",  # presets that judge success by it
        "classifier_episodes": folder / "success_session",  # the twin episodes it learnt from
    }


def eval_folder(checkpoint: Path) -> Path:
    """Where a Stage I policy's plant evaluation lies: beside it."""
    return checkpoint.with_name(f"{checkpoint.name}_eval")
