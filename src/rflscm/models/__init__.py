"""Channel models behind one contract (:mod:`rflscm.models.base`)."""

from rflscm.models import (
    nerf2,  # noqa: F401  (registers "nerf2")
    wnomp,  # noqa: F401  (registers "wnomp")
)
from rflscm.models.base import MODEL_REGISTRY, LSCMModel, UnsupportedError, load_model, register_model
from rflscm.models.rflscm import RFLSCM  # noqa: F401  (registers "rflscm")
from rflscm.models.tiled import TiledModel  # noqa: F401  (registers "tiled")

__all__ = ["MODEL_REGISTRY", "LSCMModel", "UnsupportedError", "load_model", "register_model"]
