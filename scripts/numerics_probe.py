"""Print a tiny RF-LSCM and NeRF²-LSCM training run's loss history, validation MAE and APS checksum.

Used to check that a refactoring leaves the numerics unchanged: run it before and after with
``OMP_NUM_THREADS=1 python scripts/numerics_probe.py`` and compare the outputs (issue 11).
"""

from __future__ import annotations

import sys
import tempfile

import numpy as np
import torch


def main() -> None:
    torch.set_num_threads(1)
    from rflscm.data import load_scenario
    from rflscm.data.examples import tiny_scenario
    from rflscm.geometry import AngleGrid
    from rflscm.models import MODEL_REGISTRY

    try:
        from rflscm.train import fit
    except ImportError:  # before issue 11: models fitted themselves
        fit = None
    grid = AngleGrid.full_sphere(10, 12)
    scenario = load_scenario(tiny_scenario(tempfile.mkdtemp(), seed=0))
    base = {
        "prior": {"enabled": False},
        "field": {"voxel_m": 20.0, "delta_rank": 2, "feature_rank": 2, "feature_dim": 4},
        "decoder": {"hidden": 16},
        "render": {"step_m": 8.0},
        "hitam": {"top_k": 3, "warmup_steps": 6, "ramp_steps": 4},
        "train": {
            "steps": 16,
            "batch_pairs": 4,
            "pairs_per_cell": 2,
            "val_pairs": 2,
            "val_every": 4,
            "checkpoint_every": 4,
        },
    }
    nerf2 = {
        **base,
        "field": {"hidden": 16, "layers": 3, "skip_at": 2, "pos_freqs": 2, "feature_dim": 8},
        "decoder": {"hidden": 16, "head_hidden": 8},
    }
    prior = {**base, "prior": {"enabled": True}}
    for label, name, cfg in (("rflscm", "rflscm", base), ("rflscm+prior", "rflscm", prior), ("nerf2", "nerf2", nerf2)):
        model = MODEL_REGISTRY[name].build(cfg, grid)
        history: list[float] = []
        kwargs = {"progress": False, "callback": lambda m, history=history: history.append(m["total"])}
        summary = fit(model, scenario, **kwargs) if fit is not None else model.fit(scenario, **kwargs)
        aps = model.aps(np.array([11, 11, 12]), np.array([100, 101, 102]))
        print(label, "losses", " ".join(f"{v:.9g}" for v in history))
        print(label, "val_mae_db", f"{summary['val_mae_db']:.9g}", "aps_sum", f"{float(aps.double().sum()):.9g}")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
