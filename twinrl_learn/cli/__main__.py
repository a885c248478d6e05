"""``python -m twinrl_learn.cli``: the ``twinrl`` command (how child processes start it)."""

from twinrl_learn.cli import main

main()
