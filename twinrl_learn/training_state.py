"""Training state on disk (an agent's critics and optimizers, an SFT run's optimizer and
random generators): loaded without ever running code, written whole.

``torch.load(weights_only=True)`` unpickles only tensors, numbers, strings and the
containers of them (``dict``, ``list``, ``tuple``): a state file someone shares cannot
execute anything when loaded, and a file holding anything else is refused. States are
written beside their path and renamed into place, so a kill leaves the old state or the
new one, never half of one.
"""

from __future__ import annotations

import io
import pickle
from pathlib import Path
from typing import Any

import torch

from twinrl_data.atomic import write_atomic
from twinrl_learn.errors import LearnError


def save_state(state: dict[str, Any], path: str | Path) -> None:
    """Write ``state`` (tensors, numbers, strings and containers of them) to ``path``."""
    buffer = io.BytesIO()
    torch.save(state, buffer)
    write_atomic(path, buffer.getvalue())


def load_state(path: str | Path) -> dict[str, Any]:
    """Read a state written by :func:`save_state`, refusing anything but plain data."""
    path = Path(path)
    try:
        state = torch.load(path, weights_only=True, map_location="cpu")
    except pickle.UnpicklingError as err:
        raise LearnError(
            f"{path} holds more than tensors and numbers ({str(err).splitlines()[0]}); it "
            "is refused because loading it could run code: use a checkpoint made by twinrl"
        ) from None
    except (OSError, RuntimeError, EOFError) as err:
        raise LearnError(f"{path} cannot be read as training state ({err})") from None
    if not isinstance(state, dict):
        raise LearnError(f"{path} is not a twinrl training state (a {type(state).__name__})")
    return state
