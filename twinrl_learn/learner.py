"""The learner apart from the robot loop: gradient updates in their own thread.

A robot acts at its control rate and must never wait for a gradient update (an image
policy's takes about twice the 10 Hz period). The actor (the robot loop) acts with its
own copy of the policy and, for every step it takes, *grants* the learner ``utd``
updates; the :class:`Learner` runs them in a background thread on the buffers as they
were when the episode started. Between episodes the actor hands the finished episode to
the buffers and takes the new weights (:meth:`Learner.weights`).

With ``sync=True`` the actor waits, between two episodes, until the learner has run
every update the episode granted: the run then takes exactly ``utd`` updates per robot
step, on the same data, whatever the machine's speed, so a seed gives the same run.
With ``sync=False`` it takes whatever the learner has reached (a real cell that cannot
wait); the remaining updates run during the next episode. This is the split a
distributed learner (on another machine) keeps.
"""

from __future__ import annotations

import copy
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import torch

from twinrl_data.schema import Episode
from twinrl_learn.online import OnlineRun
from twinrl_learn.policy import Policy


class Learner:
    """Runs ``run``'s updates in a thread; see the module docstring."""

    def __init__(self, run: OnlineRun) -> None:
        self.run = run
        self.metrics: dict[str, float] = {}
        self._lock = threading.Lock()  # held for each update and each boundary operation
        self._work = threading.Condition()  # guards the counters of steps and updates
        self._stopping = False
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._serve, name="twinrl-learner", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ actor side
    def grant(self, env_steps: int) -> None:
        """Count ``env_steps`` new robot steps; the learner runs the updates they buy.
        Never waits for an update in progress."""
        self._raise_if_failed()
        with self._work:
            self.run.count_steps(env_steps)
            self._work.notify()

    def wait(self, timeout_s: float | None = None) -> bool:
        """Block until every granted update has run; False if ``timeout_s`` ran out."""
        with self._work:
            done = self._work.wait_for(
                lambda: self._error is not None or not self.run.updates_due(), timeout_s
            )
        self._raise_if_failed()
        return done

    @contextmanager
    def paused(self) -> Iterator[OnlineRun]:
        """The run with no update in progress (add episodes, checkpoint, copy weights)."""
        self._raise_if_failed()
        with self._lock:
            yield self.run

    def add_episodes(self, paths: list[Path]) -> list[Episode]:
        with self.paused() as run:
            return run.add_episodes(paths)

    def weights(self) -> dict[str, torch.Tensor]:
        """A copy of the policy's current weights, for the actor to load."""
        with self.paused() as run:
            return copy.deepcopy(run.agent.policy.state_dict())

    def close(self) -> None:
        with self._work:
            self._stopping = True
            self._work.notify_all()
        self._thread.join()

    # ---------------------------------------------------------------- learner side
    def _serve(self) -> None:
        try:
            while True:
                with self._work:
                    self._work.wait_for(lambda: self._stopping or self.run.updates_due())
                    if self._stopping:
                        return
                with self._lock:
                    metrics = self.run.update()
                self.metrics = metrics
                with self._work:
                    self.run.update_done()
                    self._work.notify_all()
        except BaseException as error:  # handed to the actor at its next call
            with self._work:
                self._error = error
                self._work.notify_all()

    def _raise_if_failed(self) -> None:
        if self._error is not None:
            raise RuntimeError("the learner thread stopped with an error") from self._error


def actor_copy(policy: Policy) -> Policy:
    """The actor's own copy of ``policy`` (same weights; it never trains)."""
    actor = copy.deepcopy(policy)
    actor.requires_grad_(False)
    return actor
