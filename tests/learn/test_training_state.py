"""Training state loads without running code and is written whole."""

import pickle

import pytest
import torch

from twinrl_learn.errors import LearnError
from twinrl_learn.training_state import load_state, save_state


class Payload:
    """Unpickling this would create a file: what a hostile checkpoint could do."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (open, (str(self.marker), "w"))


def test_a_checkpoint_that_would_run_code_is_refused_without_running_it(tmp_path):
    marker = tmp_path / "ran"
    hostile = tmp_path / "agent.pt"
    torch.save({"policy": Payload(marker)}, hostile, pickle_module=pickle)
    with pytest.raises(LearnError, match="could run code"):
        load_state(hostile)
    assert not marker.exists()


def test_state_round_trips_and_a_failed_write_keeps_the_old_one(tmp_path, monkeypatch):
    path = tmp_path / "state.pt"
    generator = torch.Generator().manual_seed(3)
    state = {
        "weights": torch.arange(4.0),
        "step": 7,
        "losses": [0.5, 0.25],
        "rng": generator.get_state(),
    }
    save_state(state, path)
    loaded = load_state(path)
    assert loaded["step"] == 7 and torch.equal(loaded["weights"], state["weights"])
    assert torch.equal(loaded["rng"], state["rng"])

    def fail(*args, **kwargs):
        raise OSError(28, "No space left on device")

    import twinrl_data.atomic as atomic

    monkeypatch.setattr(atomic.os, "replace", fail)
    with pytest.raises(ValueError, match="is full"):
        save_state({"step": 8}, path)
    monkeypatch.undo()
    assert load_state(path)["step"] == 7
    assert [p.name for p in tmp_path.iterdir()] == ["state.pt"]
