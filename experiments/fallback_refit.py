"""Issue 29: give a budget-trained RF-LSCM checkpoint WNOMP's APS on the training pairs its pass did not correct.

Usage: ``PYTHONPATH=src python experiments/fallback_refit.py CKPT SCENARIO OUT`` (then ``rflscm evaluate OUT
SCENARIO``): the shipped-scenario comparison in docs/DECISIONS.md (issue 29, "Pairs the budget's pass cannot
reach"). The checkpoint's own pass is kept; WNOMP's APS is added for every training pair without an anchor,
whatever the held-aside choice would say (``scores`` records ``forced``).
"""

from __future__ import annotations

import sys
import time

import numpy as np
import pandas as pd
import torch

from rflscm.data import load_scenario
from rflscm.eval.protocols import make_protocol
from rflscm.models.base import load_model
from rflscm.models.rflscm import corrections as C
from rflscm.models.rflscm.model import RFLSCM


def main() -> None:
    torch.set_num_threads(1)
    ckpt, scen_path, out = sys.argv[1:4]
    train_scen = make_protocol("adjust").training_scenario(load_scenario(scen_path))
    model = load_model(ckpt)
    assert isinstance(model, RFLSCM) and model.corrections.anchors is not None
    fresh = RFLSCM.build(model.config)
    fresh.prepare(train_scen)  # the same training data (deterministic), for the reports and columns
    assert fresh.scene is not None
    train = fresh._training()
    d = train.data
    visible = torch.as_tensor(fresh.scene.visible)
    fit = C._Fit(model.config.corrections, d, train.num_ssb, len(fresh.scene.cell_ids), None, train.columns, visible)  # type: ignore[arg-type]
    pairs = torch.nonzero(d.observed.any(1)).squeeze(1)
    ids = np.asarray(fresh.scene.cell_ids)[d.cell_index.numpy()[pairs.numpy()]]
    index = pd.MultiIndex.from_arrays([ids, d.grid_ids[pairs.numpy()]])
    rest = pairs[~torch.as_tensor(index.isin(model.corrections.anchors.index))]
    begun = time.perf_counter()
    cell_ids = np.asarray(fresh.scene.cell_ids)
    model.corrections.fallback = fit.fallback(rest, cell_ids, model.corrections.levels, {"forced": 1.0})
    print(f"WNOMP's APS for {rest.numel()} of {pairs.numel()} pairs in {time.perf_counter() - begun:.1f} s")
    model.save(out)


if __name__ == "__main__":
    main()
