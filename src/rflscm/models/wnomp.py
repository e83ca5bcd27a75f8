"""WNOMP: the original LSCM baseline, one sparse non-negative APS per (cell, grid) (SPEC §4).

Each (cell, grid) pair with round-1 measurements is an independent sparse
recovery problem r = A x, x ≥ 0, ‖x‖₀ ≤ K_max (paper eq. (4)), solved by the
batched weighted non-negative OMP of :mod:`rflscm.models.wnomp_solver`.  The
cell's SSB and CSI-RS rows (round-1 codebooks) are stacked into one A of
M ≤ 40 beams.  The fitted APS is kept sparsely (bins + path gains per pair).

WNOMP has no notion of a grid it never measured: :meth:`WNOMPModel.aps` raises
:class:`~rflscm.models.base.UnsupportedError` for such pairs rather than guess.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Literal

import numpy as np
import pandas as pd
import torch

from rflscm.config import from_dict, load_yaml, to_dict
from rflscm.data.pair_lookup import PairLookup
from rflscm.errors import CheckpointError, ConfigError
from rflscm.geometry import AngleGrid
from rflscm.models.base import LSCMModel, UnsupportedError, register_model, require_round1_reports
from rflscm.models.wnomp_solver import wnomp_solve

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario


@dataclass(frozen=True)
class WNOMPConfig:
    """Settings of the WNOMP baseline (YAML keys = field names)."""

    KEY: ClassVar[str] = "model"
    """Where these settings usually sit (its errors name ``model.…``; :func:`~rflscm.config.from_dict` renames
    that prefix where they sit elsewhere, as in ``corrections.wnomp_fallback``)."""

    k_max: int = 8
    """Maximum number of atoms (non-zero APS bins) per (cell, grid)."""
    tolerance: float = 0.01
    """An atom is kept only if it lowers the weighted residual norm by at least this fraction."""
    residual_floor: float = 0.0
    """Stop once the weighted residual norm falls below this fraction of the target's (with ``inverse_rsrp``
    the RMS relative error: 0.25 ≈ 1 dB), so that measurement noise is not fitted; 0 = off."""
    gain_prior: float = 0.0
    """γ ∈ [0, 1]: atoms maximise ⟨ω⊙A_n, e⟩/‖ω⊙A_n‖^(1−γ); 0 = normalised correlation (textbook WNOMP);
    γ > 0 breaks the front/back mirror ambiguity of a planar array in favour of the higher-gain bin."""
    weighting: Literal["inverse_rsrp", "none"] = "inverse_rsrp"
    """``inverse_rsrp``: w_m = 1/r_m, the residual tracks relative (dB-like) error; ``none``: plain LS."""
    use_threshold_constraint: bool = False
    """Penalise missing beams predicted above the reporting threshold (one-sided, paper's L_P)."""
    num_workers: int = 0
    """Worker threads (one torch thread each); 0 = one per CPU core."""
    chunk_size: int = 512
    """(cell, grid) problems solved together; memory ≈ 8 · chunk_size · num_bins bytes per worker."""

    def __post_init__(self) -> None:
        if self.k_max < 1:
            raise ConfigError(f"`model.k_max` must be >= 1 (got {self.k_max}).")
        if not 0.0 <= self.tolerance < 1.0:
            raise ConfigError(f"`model.tolerance` must lie in [0, 1) (got {self.tolerance}).")
        if not 0.0 <= self.gain_prior <= 1.0:
            raise ConfigError(f"`model.gain_prior` must lie in [0, 1] (got {self.gain_prior}).")
        if not 0.0 <= self.residual_floor < 1.0:
            raise ConfigError(f"`model.residual_floor` must lie in [0, 1) (got {self.residual_floor}).")
        if self.num_workers < 0:
            raise ConfigError(f"`model.num_workers` must be >= 0 (0 = one per core; got {self.num_workers}).")
        if self.chunk_size < 1:
            raise ConfigError(f"`model.chunk_size` must be >= 1 (got {self.chunk_size}).")


PRESETS: dict[str, WNOMPConfig] = {"quick": WNOMPConfig(), "full": WNOMPConfig()}
"""WNOMP is already fast: both presets are the defaults."""


def wnomp_config(config: str | Path | dict[str, Any] | WNOMPConfig | None) -> WNOMPConfig:
    """A :class:`WNOMPConfig` from a preset name, a YAML path, a mapping or ``None`` (defaults).

    A mapping (or YAML file) may carry ``name: wnomp``, as a run config's ``model`` section does.
    """
    if config is None:
        return WNOMPConfig()
    if isinstance(config, WNOMPConfig):
        return config
    if isinstance(config, str) and config in PRESETS:
        return PRESETS[config]
    if isinstance(config, (str, Path)):
        path = Path(config)
        if path.suffix.lower() not in (".yaml", ".yml") and not path.is_file():
            raise ConfigError(
                f"WNOMP config {str(config)!r} is neither a preset ({', '.join(PRESETS)}) nor a YAML file."
            )
        data = load_yaml(path)
        try:
            return wnomp_config(data)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None
    data = dict(config)
    name = data.pop("name", "wnomp")
    if name != "wnomp":
        raise ConfigError(f"`model.name` is {name!r} but this config is for the `wnomp` model.")
    return from_dict(WNOMPConfig, data, prefix="model")


@register_model
class WNOMPModel(LSCMModel):
    """Weighted non-negative OMP per (cell, grid) (the original LSCM; SPEC §4)."""

    name = "wnomp"
    supports_unseen_grids = False

    def __init__(self, config: WNOMPConfig, angle_grid: AngleGrid, device: torch.device | str = "cpu") -> None:
        super().__init__(angle_grid, device)
        self.config = config
        self.cell_ids = np.zeros(0, dtype=np.int64)  # [num_pairs]
        self.grid_ids = np.zeros(0, dtype=np.int64)  # [num_pairs]
        self.indices = torch.zeros((0, config.k_max), dtype=torch.int32)  # [num_pairs, k_max], −1 = unused
        self.values = torch.zeros((0, config.k_max), dtype=torch.float32)  # [num_pairs, k_max] path gain
        self._lookup = PairLookup(self.cell_ids, self.grid_ids)

    @classmethod
    def build(
        cls, config: str | Path | dict[str, Any] | None, angle_grid: AngleGrid, device: torch.device | str
    ) -> WNOMPModel:
        return cls(wnomp_config(config), angle_grid, device)

    # --- fitting ------------------------------------------------------------------------------
    def fit(
        self,
        scenario: Scenario,
        progress: bool = True,
        callback: Callable[[dict[str, float]], None] | None = None,
        checkpoint_path: str | Path | None = None,
        resume: bool = False,
    ) -> dict[str, float]:
        """Solve every (cell, grid) pair of the round-1 measurements; ``resume`` is meaningless here."""
        start = time.perf_counter()
        require_round1_reports(scenario, "WNOMP")
        pairs, rsrp_dbm, beams_of_cell = round1_problems(scenario)
        threshold_mw = (
            10.0 ** (scenario.meta.rsrp_threshold_dbm / 10.0) if self.config.use_threshold_constraint else None
        )
        cell_of_pair = pairs["cell_id"].to_numpy()
        matrices = CellMatrices(lambda cell: _stacked_sensing(scenario, cell, self.angle_grid, self.device))
        jobs = []
        for cell in np.unique(cell_of_pair):
            rows = np.flatnonzero(cell_of_pair == cell)
            rsrp_mw = 10.0 ** (rsrp_dbm[rows][:, beams_of_cell[int(cell)]] / 10.0)  # NaN stays NaN
            for s in range(0, len(rows), self.config.chunk_size):
                jobs.append((int(cell), rows[s : s + self.config.chunk_size], rsrp_mw[s : s + self.config.chunk_size]))
                matrices.expect(int(cell))
        indices = np.full((len(pairs), self.config.k_max), -1, dtype=np.int64)
        values = np.zeros((len(pairs), self.config.k_max), dtype=np.float64)
        done = 0
        for rows, idx, val in solve_jobs(jobs, matrices, self.config, threshold_mw, self.device, progress):
            indices[rows], values[rows] = idx, val
            done += len(rows)
            if callback is not None:
                callback({"pairs_done": float(done), "pairs_total": float(len(pairs))})
        keep = (indices >= 0).any(1)  # pairs with no reported beam (or no positive fit) stay unseen
        self._store(pairs["cell_id"].to_numpy()[keep], pairs["grid_id"].to_numpy()[keep], indices[keep], values[keep])
        elapsed = time.perf_counter() - start
        summary = {
            "train_time_s": elapsed,
            "num_pairs": float(keep.sum()),
            "pairs_per_s": float(len(pairs) / max(elapsed, 1e-9)),
            "mean_atoms": float((indices[keep] >= 0).sum(1).mean()) if keep.any() else 0.0,
        }
        self.run_info.setdefault("fit", {}).update(summary)
        if checkpoint_path is not None:
            self.save(checkpoint_path)
        return summary

    def _store(self, cell_ids: np.ndarray, grid_ids: np.ndarray, indices: np.ndarray, values: np.ndarray) -> None:
        order = np.lexsort((grid_ids, cell_ids))
        self.cell_ids = np.asarray(cell_ids, dtype=np.int64)[order]
        self.grid_ids = np.asarray(grid_ids, dtype=np.int64)[order]
        self.indices = torch.as_tensor(indices[order], dtype=torch.int32)
        self.values = torch.as_tensor(np.clip(values[order], 0.0, None), dtype=torch.float32)
        self._lookup = PairLookup(self.cell_ids, self.grid_ids)

    # --- answering ----------------------------------------------------------------------------
    def aps(self, cell_ids: np.ndarray, grid_ids: np.ndarray, grid_xyz: np.ndarray | None = None) -> torch.Tensor:
        """Dense APS ``[num_pairs, num_bins]`` (float32, linear path gain) of fitted pairs only."""
        cell_ids = np.asarray(cell_ids, dtype=np.int64).reshape(-1)
        grid_ids = np.asarray(grid_ids, dtype=np.int64).reshape(-1)
        rows = self._lookup.rows(cell_ids, grid_ids)
        if (rows < 0).any():
            bad = np.flatnonzero(rows < 0)
            examples = ", ".join(f"(cell {cell_ids[i]}, grid {grid_ids[i]})" for i in bad[:3])
            raise UnsupportedError(
                f"WNOMP has no notion of unseen grids: {len(bad)} of {len(rows)} requested (cell, grid) pairs had no "
                f"round-1 measurements to fit, e.g. {examples}; use a field model (rflscm, nerf2) to predict them."
            )
        idx = self.indices[rows].long()
        val = self.values[rows]
        out = torch.zeros((len(rows), self.angle_grid.num_bins), dtype=torch.float32)
        out.scatter_add_(1, idx.clamp_min(0), torch.where(idx >= 0, val, 0.0))
        return out.to(self.device)

    # --- persistence --------------------------------------------------------------------------
    def state_dict_for_checkpoint(self) -> dict[str, Any]:
        return {
            "config": to_dict(self.config),
            "cell_ids": torch.as_tensor(self.cell_ids),
            "grid_ids": torch.as_tensor(self.grid_ids),
            "indices": self.indices,
            "values": self.values,
        }

    def check_loaded(self) -> None:
        """Pairs, indices and values agree in length and every stored bin index lies on the angle grid."""
        n, k = len(self.cell_ids), self.config.k_max
        shapes = (len(self.grid_ids), tuple(self.indices.shape), tuple(self.values.shape))
        if shapes != (n, (n, k), (n, k)):
            raise CheckpointError(
                f"the WNOMP arrays do not agree ({n} cells, {shapes[0]} grids, indices {shapes[1]}, values "
                f"{shapes[2]}, k_max {k}); the file is damaged: retrain it."
            )
        bins = self.angle_grid.num_bins
        bad = (self.indices < -1) | (self.indices >= bins)
        if bool(bad.any()):
            value = int(self.indices[bad][0])
            raise CheckpointError(
                f"a stored APS bin index ({value}) lies outside the angle grid's 0…{bins - 1} (−1 = unused) in "
                f"{int(bad.sum())} place(s); the file is damaged: retrain it."
            )
        if bool((self.values < 0).any()):
            raise CheckpointError("stored APS path gains are negative; the file is damaged: retrain it.")

    @classmethod
    def from_checkpoint(cls, state: dict[str, Any], device: torch.device | str = "cpu") -> WNOMPModel:
        model = cls(from_dict(WNOMPConfig, state["config"], prefix="model"), AngleGrid(), device)
        model._store(
            state["cell_ids"].numpy(),
            state["grid_ids"].numpy(),
            state["indices"].numpy(),
            state["values"].double().numpy(),
        )
        return model


def round1_problems(scenario: Scenario) -> tuple[pd.DataFrame, np.ndarray, dict[int, np.ndarray]]:
    """All round-1 (cell, grid) pairs with their stacked SSB + CSI-RS RSRP.

    Returns:
        ``(pairs, rsrp_dbm, beams_of_cell)``: ``pairs`` (``cell_id``, ``grid_id``) sorted;
        ``rsrp_dbm [num_pairs, max_ssb + max_csi]`` (NaN = missing); ``beams_of_cell[c]`` the
        column indices of cell c's SSB then CSI-RS beams, matching :func:`_stacked_sensing`'s rows.
    """
    p_ssb, r_ssb = scenario.rsrp_table(1, "ssb")
    p_csi, r_csi = scenario.rsrp_table(1, "csi")
    pairs = pd.concat([p_ssb, p_csi]).drop_duplicates().sort_values(["cell_id", "grid_id"], ignore_index=True)
    index = pd.MultiIndex.from_frame(pairs)
    ssb_w, csi_w = r_ssb.shape[1], r_csi.shape[1]
    rsrp = np.full((len(pairs), ssb_w + csi_w), np.nan)
    rsrp[index.get_indexer(pd.MultiIndex.from_frame(p_ssb)), :ssb_w] = r_ssb
    rsrp[index.get_indexer(pd.MultiIndex.from_frame(p_csi)), ssb_w:] = r_csi
    beams = {}
    for cell in np.unique(pairs["cell_id"].to_numpy()):
        n_ssb = scenario.num_beams(int(cell), "ssb", 1)
        n_csi = scenario.num_beams(int(cell), "csi", 1)
        beams[int(cell)] = np.concatenate([np.arange(n_ssb), ssb_w + np.arange(n_csi)])
    return pairs, rsrp, beams


def _stacked_sensing(scenario: Scenario, cell_id: int, angle_grid: AngleGrid, device: torch.device) -> torch.Tensor:
    """Round-1 SSB rows over CSI-RS rows: ``A [num_ssb + num_csi, num_bins]`` [mW per unit gain].

    float32, as :meth:`LSCMModel.predict_rsrp` uses, so that fit and prediction see the same A.
    """
    parts = [scenario.sensing(cell_id, bt, angle_grid, round=1, device=device) for bt in ("ssb", "csi")]
    return torch.cat(parts, dim=0)


class CellMatrices:
    """Sensing matrices computed once per cell on first use (thread-safe) and dropped after the last job."""

    def __init__(self, make: Callable[[int], torch.Tensor]) -> None:
        self._make = make
        self._lock = threading.Lock()
        self._locks: dict[int, threading.Lock] = {}
        self._cache: dict[int, torch.Tensor] = {}
        self._pending: dict[int, int] = {}

    def expect(self, cell: int) -> None:
        self._pending[cell] = self._pending.get(cell, 0) + 1
        self._locks.setdefault(cell, threading.Lock())

    def get(self, cell: int) -> torch.Tensor:
        with self._locks[cell]:
            if cell not in self._cache:
                self._cache[cell] = self._make(cell)
            return self._cache[cell]

    def release(self, cell: int) -> None:
        with self._lock:
            self._pending[cell] -= 1
            if self._pending[cell] == 0:
                self._cache.pop(cell, None)


def solve_jobs(
    jobs: list[tuple[int, np.ndarray, np.ndarray]],
    matrices: CellMatrices,
    config: WNOMPConfig,
    threshold_mw: float | None,
    device: torch.device,
    progress: bool = False,
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Run WNOMP on ``jobs`` = ``(cell, rows, rsrp_mw [len(rows), M])`` over ``config.num_workers`` threads.

    Yields ``(rows, indices [len(rows), k_max], values [len(rows), k_max])`` as jobs finish (in order).
    """

    def solve(job: tuple[int, np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        cell, rows, rsrp_mw = job
        a = matrices.get(cell)
        r = torch.as_tensor(rsrp_mw, dtype=torch.float64, device=a.device)
        idx, val = wnomp_solve(
            a,
            r,
            config.k_max,
            config.tolerance,
            config.weighting,
            threshold_mw,
            config.chunk_size,
            config.residual_floor,
            config.gain_prior,
        )
        matrices.release(cell)
        return rows, idx.cpu().numpy(), val.cpu().numpy()

    with _worker_pool(config.num_workers, torch.device(device)) as pool:
        yield from _progress(pool.map(solve, jobs), len(jobs), progress)


class _worker_pool:
    """Thread pool with one torch thread per worker on CPU (torch ops release the GIL), inline on GPU.

    Threads rather than torch's intra-op parallelism: the solver runs many small ops, whose
    OpenMP barriers stall badly when the cores are shared with other processes.
    """

    def __init__(self, num_workers: int, device: torch.device) -> None:
        self.device = device
        self.workers = 1 if device.type != "cpu" else (num_workers or _num_cores())
        self.saved_threads = torch.get_num_threads()
        self.pool: ThreadPoolExecutor | None = None

    def __enter__(self) -> _worker_pool:
        if self.device.type == "cpu":
            torch.set_num_threads(1)
        if self.workers > 1:
            self.pool = ThreadPoolExecutor(self.workers)
        return self

    def map(self, fn: Callable, jobs: list) -> Any:
        return self.pool.map(fn, jobs) if self.pool is not None else map(fn, jobs)

    def __exit__(self, *exc: object) -> None:
        if self.pool is not None:
            self.pool.shutdown()
        torch.set_num_threads(self.saved_threads)


def _progress(items: Any, total: int, enabled: bool) -> Any:
    if not enabled:
        return items
    from tqdm import tqdm

    return tqdm(items, total=total, desc="wnomp", unit="chunk", leave=False)


def _num_cores() -> int:
    """CPU cores this process may run on (the affinity mask, not the host's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - macOS / Windows
        return os.cpu_count() or 1
