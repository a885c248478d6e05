"""The sim-to-real gap workflow: replay measured episodes in the twin, localise where
they disagree, fit and name the effects the twin lacks, and show the gap shrink."""

from twinrl_sim.gap.diagnose import IMAGE_EFFECTS as IMAGE_EFFECTS
from twinrl_sim.gap.diagnose import Diagnosis as Diagnosis
from twinrl_sim.gap.diagnose import diagnose as diagnose
from twinrl_sim.gap.identify import CANDIDATES as CANDIDATES
from twinrl_sim.gap.identify import NoiseFloor as NoiseFloor
from twinrl_sim.gap.localize import Disagreement as Disagreement
from twinrl_sim.gap.localize import localize as localize
from twinrl_sim.gap.localize import plot_localization as plot_localization
from twinrl_sim.gap.report import write_report as write_report
from twinrl_sim.gap.shooting import ShootingReplay as ShootingReplay
from twinrl_sim.gap.shooting import replay_windows as replay_windows
