"""A trained RF-LSCM checkpoint rebuilt just before its pass after training, for the experiments that rerun that pass
(``refit_pass.py``, ``pass_steps.py``; run them from the repository root, which puts this folder on the path)."""

import torch

from rflscm.data.scenario import Scenario
from rflscm.eval.protocols import AdjustProtocol
from rflscm.models import load_model
from rflscm.models.base import read_checkpoint
from rflscm.models.rflscm import RFLSCM


def model_before_its_pass(scenario: Scenario, checkpoint: str) -> RFLSCM:
    """The checkpoint's RF-LSCM with its trained weights and its training data prepared on ``scenario``'s round 1, as
    ``finish_training`` finds it at the end of training (seed 0)."""
    loaded = load_model(checkpoint, scenario)
    torch.manual_seed(0)
    model = RFLSCM(loaded.config, loaded.angle_grid)
    model.fingerprint, model.run_info = loaded.fingerprint, dict(loaded.run_info)
    model.prepare(AdjustProtocol().training_scenario(scenario))
    model.resume_from(read_checkpoint(checkpoint), checkpoint)
    return model
