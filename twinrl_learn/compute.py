"""Where the networks run: the CPU, or a CUDA GPU with mixed precision.

Every command that trains or runs a network takes ``--device auto|cpu|cuda`` (``auto``:
a GPU when torch sees one, else the CPU). Checkpoints are always written from and read
onto the CPU first, so a policy trained on a GPU loads on a machine without one and the
other way round. On a GPU the forward passes run under bfloat16 autocast (matrix
products and convolutions in bfloat16, reductions and losses in float32), which needs no
loss scaling; on the CPU everything stays float32, so a seed gives the same run as before.

:func:`check_device` reads the name only (no torch import), for the settings records;
:func:`resolve_device` also checks that the machine has what was asked for.
"""

from __future__ import annotations

import re
from contextlib import AbstractContextManager, nullcontext
from typing import TYPE_CHECKING

from twinrl_data.errors import SettingError

if TYPE_CHECKING:
    import torch

_NAME = re.compile(r"^(auto|cpu|cuda(:\d+)?)$")


def check_device(name: str) -> None:
    """Refuse a device name that is not auto, cpu, cuda or cuda:N."""
    if not isinstance(name, str) or not _NAME.match(name):
        raise SettingError("device", f"must be auto, cpu, cuda or cuda:N, got '{name}'")


def resolve_device(name: str | torch.device) -> torch.device:
    """The torch device ``name`` stands for on this machine (a device is itself); asking
    for a GPU on a machine without a usable one is an error that says so."""
    import torch

    if isinstance(name, torch.device):
        return name
    check_device(name)
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise SettingError(
                "device", f"is {name} but torch sees no CUDA GPU on this machine; use auto or cpu"
            )
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise SettingError(
                "device",
                f"is {name} but this machine has {torch.cuda.device_count()} GPU(s); "
                "use cuda:0 or auto",
            )
    return device


def mixed_precision(device: torch.device) -> AbstractContextManager:
    """bfloat16 autocast for forward passes on a GPU; nothing on the CPU."""
    import torch

    if device.type == "cuda":
        return torch.autocast("cuda", dtype=torch.bfloat16)
    return nullcontext()


def module_device(module: torch.nn.Module) -> torch.device:
    """The device a module's parameters (or buffers) live on; the CPU when it has none."""
    import torch

    for tensor in module.parameters():
        return tensor.device
    for tensor in module.buffers():
        return tensor.device
    return torch.device("cpu")
