"""The errors of the learners and studies: every one says what is wrong and how to fix it."""

from twinrl_data.errors import TwinrlError


class LearnError(TwinrlError):
    """A setting, a checkpoint, a dataset or a run cannot be used as given by a learner."""
