"""The oracle: the evaluation floor, answering with the true APS of a simulated scenario.

It is an evaluation device, not a model: an :class:`~rflscm.models.source.APSSource` built by
:func:`rflscm.eval.run_evaluation` (``oracle="auto"``) and by the benchmark harness, never registered in
:data:`rflscm.models.MODEL_REGISTRY`, never trained and never saved.  It reads the scenario's ``truth/`` folder
(:mod:`rflscm.sim.truth`) — the only place that may — and predicts RSRP with the models' shared
:func:`~rflscm.models.source.predict_rsrp`, so what remains of its MAE is angular binning and measurement noise.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import torch

from rflscm.errors import UnsupportedError
from rflscm.geometry import AngleGrid
from rflscm.models.base import content_hash
from rflscm.models.source import Predicts
from rflscm.sim.truth import TrueAPS, load_true_aps

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario


class OracleModel(Predicts):
    """The true APS of a simulated scenario behind ``aps`` / ``predict_rsrp``.

    Pairs the simulation did not trace raise :class:`UnsupportedError`.
    """

    name: ClassVar[str] = "oracle"
    supports_unseen_grids: ClassVar[bool] = True

    def __init__(self, angle_grid: AngleGrid, device: torch.device | str = "cpu", sample_round: int | None = None):
        self.angle_grid = angle_grid
        self.device = torch.device(device)
        self.sample_round = sample_round
        """Answer with the APS of that round's UE samples where truth/ has it (field regime)."""
        self.fingerprint: str | None = None
        self.run_info: dict[str, Any] = {}
        self._truth: TrueAPS | None = None

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
        oracle = cls(angle_grid, device, sample_round)
        oracle.read(scenario)
        return oracle

    def read(self, scenario: Scenario) -> OracleModel:
        """Read the true APS of ``scenario`` (a :class:`DataError` without ``truth/``)."""
        self._truth = load_true_aps(scenario, self.angle_grid, self.sample_round)
        self.fingerprint = scenario.fingerprint()
        return self

    def content_sha256(self) -> str:
        """The oracle's cache key: its scenario, grid and sample round (:func:`rflscm.models.source.source_sha256`)."""
        key = {"model": self.name, "fingerprint": self.fingerprint, "sample_round": self.sample_round}
        return content_hash({**key, "angle_grid": self.angle_grid.to_dict()})

    def aps(self, cell_ids: np.ndarray, grid_ids: np.ndarray, grid_xyz: np.ndarray | None = None) -> torch.Tensor:
        if self._truth is None:
            raise UnsupportedError(
                "the oracle has not read its truth; build it with OracleModel.for_scenario(scenario, grid)."
            )
        return self._truth.aps(cell_ids, grid_ids, dtype=torch.float32, device=self.device)

    def level_offset_db(
        self, cell_ids: np.ndarray, beam_type: str, grid_ids: np.ndarray | None = None
    ) -> np.ndarray | None:
        return None
