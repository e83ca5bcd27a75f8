"""The oracle: the evaluation floor, answering with the true APS of a simulated scenario.

It is an evaluation device, not a model: it is built by :func:`rflscm.eval.run_evaluation`
(``oracle="auto"``) and by the benchmark harness, never registered in
:data:`rflscm.models.MODEL_REGISTRY`, never trained by ``rflscm train`` and never saved.  It reads
the scenario's ``truth/`` folder (:mod:`rflscm.sim.truth`) — the only place that may — and predicts
RSRP with the models' shared :meth:`~rflscm.models.LSCMModel.predict_rsrp`, so what remains of its
MAE is angular binning and measurement noise.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from rflscm.errors import ConfigError, UnsupportedError
from rflscm.geometry import AngleGrid
from rflscm.models.base import LSCMModel
from rflscm.sim.truth import TrueAPS, load_true_aps

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario


class OracleModel(LSCMModel):
    """The true APS of a simulated scenario behind the model contract's ``aps``/``predict_rsrp``.

    Pairs the simulation did not trace raise :class:`UnsupportedError`.
    """

    name = "oracle"

    def __init__(self, angle_grid: AngleGrid, device: torch.device | str = "cpu") -> None:
        super().__init__(angle_grid, device)
        self._truth: TrueAPS | None = None
        self.sample_round: int | None = None
        """Set before ``fit``: answer with the APS of that round's UE samples where truth/ has it (field regime)."""

    @classmethod
    def build(
        cls, config: str | Path | dict[str, Any] | None, angle_grid: AngleGrid, device: torch.device | str
    ) -> OracleModel:
        if config not in (None, "quick", "full") and config != {}:
            raise ConfigError(f"the oracle has no settings (got {config!r}).")
        return cls(angle_grid, device)

    @classmethod
    def for_scenario(
        cls,
        scenario: Scenario,
        angle_grid: AngleGrid,
        device: torch.device | str = "cpu",
        sample_round: int | None = None,
    ) -> OracleModel:
        """The oracle of ``scenario`` on ``angle_grid`` (a :class:`DataError` without ``truth/``); with
        ``sample_round``, the APS of that round's own UE samples where the truth folder has them (field regime)."""
        oracle = cls(angle_grid, device)
        oracle.sample_round = sample_round
        oracle.fit(scenario, progress=False)
        return oracle

    def fit(
        self, scenario: Scenario, progress: bool = True, callback: Callable[[dict[str, float]], None] | None = None,
        checkpoint_path: str | Path | None = None, resume: bool = False,
    ) -> dict[str, float]:  # fmt: skip
        """Read the true APS of ``scenario`` (``progress``, ``callback``, ``resume`` do not apply)."""
        if checkpoint_path is not None:
            raise UnsupportedError("the oracle is rebuilt from truth/ by evaluation; it has no checkpoint.")
        self._truth = load_true_aps(scenario, self.angle_grid, self.sample_round)
        if self.fingerprint is None:
            self.fingerprint = scenario.fingerprint()
        return {"train_time_s": 0.0}

    def aps(self, cell_ids: np.ndarray, grid_ids: np.ndarray, grid_xyz: np.ndarray | None = None) -> torch.Tensor:
        if self._truth is None:
            raise UnsupportedError(
                "the oracle has not been fitted; build it with OracleModel.for_scenario(scenario, grid)."
            )
        return self._truth.aps(cell_ids, grid_ids, dtype=torch.float32, device=self.device)

    def state_dict_for_checkpoint(self) -> dict[str, Any]:
        raise UnsupportedError("the oracle is rebuilt from truth/ by evaluation; it has no checkpoint.")

    @classmethod
    def from_checkpoint(cls, state: dict[str, Any], device: torch.device | str = "cpu") -> OracleModel:
        raise UnsupportedError("the oracle is rebuilt from truth/ by evaluation; it has no checkpoint.")
