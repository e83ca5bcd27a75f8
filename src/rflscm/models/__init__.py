"""Channel models behind one contract (:mod:`rflscm.models.base`)."""

from rflscm.models.base import MODEL_REGISTRY, LSCMModel, UnsupportedError, load_model, register_model

__all__ = ["MODEL_REGISTRY", "LSCMModel", "UnsupportedError", "load_model", "register_model"]
