"""Training: :func:`fit` (the one way to learn a model from a scenario) and the generic :class:`Trainer`.

The loss and the pair data the models train on live with the models (:mod:`rflscm.models.rflscm.losses`,
:mod:`rflscm.models.pairs`) and are re-exported here.
"""

from rflscm.models.pairs import PairData, build_pair_data, stacked_sensing
from rflscm.models.rflscm.losses import lscm_loss, mae_db
from rflscm.train.trainer import Trainable, Trainer, TrainingPlan, fit

__all__ = [
    "PairData",
    "Trainable",
    "Trainer",
    "TrainingPlan",
    "build_pair_data",
    "fit",
    "lscm_loss",
    "mae_db",
    "stacked_sensing",
]
