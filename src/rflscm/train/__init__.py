"""Training of radiance-field LSCM models: data, losses and a generic trainer."""

from rflscm.train.data import PairData, build_pair_data, stacked_sensing
from rflscm.train.losses import lscm_loss, mae_db
from rflscm.train.trainer import Trainer

__all__ = ["PairData", "Trainer", "build_pair_data", "lscm_loss", "mae_db", "stacked_sensing"]
