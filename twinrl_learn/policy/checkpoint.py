"""The policy checkpoint: a folder that runs no code when loaded::

CKPT/
  config.json          PolicyConfig, normalisation stats, instruction embeddings
  model.safetensors    weights
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save

from twinrl_data.atomic import write_atomic
from twinrl_learn.errors import LearnError
from twinrl_learn.policy.config import KINDS, PolicyConfig

CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"


def save_checkpoint(path: str | Path, config: PolicyConfig, weights: dict[str, Any]) -> Path:
    """Write ``config`` and ``weights`` (a state dict) into the folder ``path``, each file
    whole (written beside its name and renamed into place: a kill leaves the old file or
    the new one)."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    write_atomic(path / WEIGHTS_FILE, save({k: v.contiguous() for k, v in weights.items()}))
    write_atomic(path / CONFIG_FILE, json.dumps(asdict(config), indent=1).encode())
    return path


def load_checkpoint(path: str | Path) -> tuple[PolicyConfig, dict[str, torch.Tensor]]:
    """The config and weights of a checkpoint folder; a folder that is not one is an
    error naming what it lacks."""
    path = Path(path)
    if not (path / CONFIG_FILE).is_file() or not (path / WEIGHTS_FILE).is_file():
        raise LearnError(
            f"{path} is not a twinrl policy checkpoint (needs {CONFIG_FILE} and {WEIGHTS_FILE})"
        )
    config = PolicyConfig(**json.loads((path / CONFIG_FILE).read_text()))
    return config, load_file(path / WEIGHTS_FILE)


def is_checkpoint(path: str | Path) -> bool:
    """Whether ``path`` is a twinrl policy checkpoint (lerobot's have a ``type`` instead)."""
    path = Path(path)
    if not ((path / CONFIG_FILE).is_file() and (path / WEIGHTS_FILE).is_file()):
        return False
    try:
        return json.loads((path / CONFIG_FILE).read_text()).get("kind") in KINDS
    except json.JSONDecodeError:
        return False
