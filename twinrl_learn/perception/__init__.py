"""Perception from the twin: a pose estimator on a frozen pretrained image encoder,
trained on twin renders, that tells an image policy where the objects are."""

from twinrl_learn.perception.estimator import EstimatorConfig as EstimatorConfig
from twinrl_learn.perception.estimator import PoseEstimator as PoseEstimator
from twinrl_learn.perception.training import train_estimator as train_estimator
from twinrl_learn.settings import PerceptionSettings as PerceptionSettings
