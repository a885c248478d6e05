"""The twin's commands, one module per group: :mod:`.sim` (``twinrl sim``), :mod:`.gap`,
:mod:`.twin`, and the top-level :mod:`.view` and :mod:`.expand`, with
:mod:`.import_csv` (added to ``twinrl data``)."""

from twinrl_sim.cli.expand import expand_command as expand_command
from twinrl_sim.cli.gap import gap_app as gap_app
from twinrl_sim.cli.import_csv import import_csv_command as import_csv_command
from twinrl_sim.cli.sim import app as app
from twinrl_sim.cli.twin import twin_app as twin_app
from twinrl_sim.cli.view import view as view
