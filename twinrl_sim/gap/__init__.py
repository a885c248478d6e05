"""The sim-to-real gap workflow: replay measured episodes in the twin, localise where
they disagree (this package so far), then fit and name missing effects."""

from twinrl_sim.gap.localize import Disagreement as Disagreement
from twinrl_sim.gap.localize import localize as localize
from twinrl_sim.gap.shooting import ShootingReplay as ShootingReplay
from twinrl_sim.gap.shooting import replay_windows as replay_windows
