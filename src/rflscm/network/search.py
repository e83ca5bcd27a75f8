"""Search for antenna settings on cached APS: the evaluator, coordinate descent, and scipy's DE.

:class:`NetworkEvaluator` holds the best-beam power of every cell under the current configuration and
scores a batch of single-cell candidates with one batched sensing build and one matrix product
(no loop over grids).  Objectives (docs/DECISIONS.md, "Optimisation"):

* ``coverage``: coverage ratio, ties broken by the mean RSRP margin (RSRP − threshold)/10 dB clipped
  to ±1, weighted so that its whole range is worth less than one grid;
* ``sinr``: mean SS-SINR [dB], each grid's SINR clipped to −20…30 dB;
* ``weighted``: coverage ratio + ``sinr_weight`` × mean clipped SINR / 10 dB (default 0.1: 1 dB of
  mean SINR is worth 1 % coverage).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from rflscm.errors import ConfigError
from rflscm.network.candidates import ApsCache, CellSensing, best_beam_power
from rflscm.network.kpi import (
    KPIConfig,
    area_kpis,
    carrier_groups,
    carrier_samples,
    network_kpis,
    objective_sums,
)
from rflscm.network.space import SHARED_VARIABLES, VARIABLES, SearchSpace

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario

OBJECTIVES = ("coverage", "sinr", "weighted")
Config = list[tuple[int, ...]]


def objective_value(kpis: dict[str, torch.Tensor], objective: str, sinr_weight: float = 0.1) -> torch.Tensor:
    """The scalar to maximise ``[...]`` from :func:`~rflscm.network.kpi.area_kpis` output."""
    if objective == "coverage":
        return kpis["coverage"] + 0.4 / kpis["num_samples"] * kpis["margin"]
    if objective == "sinr":
        return kpis["mean_sinr_clipped_db"]
    if objective == "weighted":
        return kpis["coverage"] + sinr_weight * kpis["mean_sinr_clipped_db"] / 10.0
    raise ConfigError(f"--objective must be one of {', '.join(OBJECTIVES)} (got {objective!r}).")


class NetworkEvaluator:
    """Scores configurations of the network on cached APS.

    Args:
        scenario: the scenario; base_round: the configuration the search starts from.
        cache: the model's APS (:meth:`~rflscm.eval.cache.ScenarioAPS.render`).
        space: the search space (its cells in the order of ``cache.cell_ids``).
        kpi: KPI constants; objective: ``coverage``, ``sinr`` or ``weighted``.
        grid_mask: ``[num_grids]`` grids the objective scores (None: all); the others are held out.
    """

    def __init__(
        self,
        scenario: Scenario,
        base_round: int,
        cache: ApsCache,
        space: SearchSpace,
        kpi: KPIConfig,
        objective: str = "coverage",
        sinr_weight: float = 0.1,
        grid_mask: np.ndarray | None = None,
    ) -> None:
        objective_value(
            {
                "coverage": torch.zeros(1),
                "num_samples": torch.ones(1),
                "margin": torch.zeros(1),
                "mean_sinr_clipped_db": torch.zeros(1),
            },
            objective,
        )  # validates the name
        self.cache, self.space, self.kpi = cache, space, kpi
        self.objective, self.sinr_weight = objective, sinr_weight
        self.freqs = np.array([scenario.freq_hz(int(c)) for c in cache.cell_ids])
        self.groups = carrier_groups(self.freqs)
        self.group_of = np.zeros(len(cache.cell_ids), dtype=np.int64)
        for g, (_, rows) in enumerate(self.groups):
            self.group_of[rows] = g
        self.noise_mw = [10.0 ** (kpi.noise_per_re_dbm(f) / 10.0) for f, _ in self.groups]
        known = cache.known if grid_mask is None else cache.known & np.asarray(grid_mask, dtype=bool)[None, :]
        self.known_np = known
        """Pairs the objective scores: the model's known pairs on the grids of ``grid_mask`` (the rest held out)."""
        self.known = torch.as_tensor(known)
        self.all_known = bool(known.all())
        self._rows = [None if row.all() else torch.as_tensor(np.flatnonzero(row)) for row in cache.known]
        """Per cell, the grid positions its cached APS rows stand for (None: every grid)."""
        dirs = cache.angle_grid.directions(dtype=torch.float32)
        self.sensing = [
            CellSensing(scenario, int(c), base_round, dirs[torch.as_tensor(cache.bins[i])], space.cells[i])
            for i, c in enumerate(cache.cell_ids)
        ]
        self.base: Config = [c.current for c in space.cells]
        self.evaluations = 0
        self.config: Config = list(self.base)
        self.power = torch.stack([self._powers(i, [idx])[0] for i, idx in enumerate(self.base)])
        self._samples = [self._carrier(g, self.power[rows]) for g, (_, rows) in enumerate(self.groups)]
        self._score: float | None = None
        """The current objective, kept until a cell moves (:meth:`score_moves` adds each move's change to it)."""
        self._count = float(sum(int(s["valid"].sum()) for s in self._samples))
        """Valid (grid, carrier) samples: the objective's denominator, the same in every configuration."""

    # --- building blocks -----------------------------------------------------------------------------
    def _powers(self, pos: int, indices: Config) -> torch.Tensor:
        """Best-beam power ``[num_candidates, num_grids]`` [mW] of cell ``pos`` under candidate indices (zero at
        the grids out of the cell's reach, which its cached APS has no row for)."""
        self.evaluations += len(indices)
        power = best_beam_power(self.cache.aps[pos], self.sensing[pos].matrices(indices), self.cache.mix_of(pos))
        rows = self._rows[pos]
        if rows is None:
            return power
        full = power.new_zeros(len(indices), len(self.cache.grid_ids))
        full[:, rows] = power
        return full

    def _carrier(self, g: int, power: torch.Tensor) -> dict[str, torch.Tensor]:
        rows = self.groups[g][1]
        known = None if self.all_known else self.known[torch.as_tensor(rows)]
        return carrier_samples(power, self.noise_mw[g], known, self.kpi)

    def num_changed(self, config: Config | None = None) -> int:
        config = self.config if config is None else config
        return sum(a != b for a, b in zip(config, self.base))

    # --- scoring -----------------------------------------------------------------------------------------
    def score_cell(self, pos: int, indices: Config) -> torch.Tensor:
        """Objective ``[num_candidates]`` of the current configuration with cell ``pos`` set to each candidate."""
        return self.score_moves([{pos: tuple(i)} for i in indices])

    def score_moves(self, moves: list[dict[int, tuple[int, ...]]]) -> torch.Tensor:
        """Objective ``[num_moves]`` of the current configuration with each move applied; every move sets the
        same cells (e.g. the cells of one antenna panel, which may lie on different carriers).

        Where the moved cells' APS cover only some grids (a large network: the grids in reach), only those grids
        are scored again: the objective moves by the change of its per-sample terms there
        (:func:`~rflscm.network.kpi.objective_sums`), added to the current objective, so a move that changes
        nothing scores the current objective exactly and the work per move follows the cells' reach, not the
        network."""
        positions = list(moves[0])
        n = len(moves)
        cand = {p: self._powers(p, [m[p] for m in moves]) for p in positions}  # [C, num_grids] each
        if any(self._rows[p] is None for p in positions):
            samples = list(self._samples)
            for g in sorted({int(self.group_of[p]) for p in positions}):
                rows = self.groups[g][1]
                power = self.power[torch.as_tensor(rows)].unsqueeze(0).repeat(n, 1, 1)  # [C, n_g, grids]
                for p in positions:
                    if int(self.group_of[p]) == g:
                        power[:, int(np.flatnonzero(rows == p)[0])] = cand[p]
                samples[g] = self._carrier(g, power)
            samples = [_expand(s, n) for s in samples]
            kpis = area_kpis(samples, self.kpi, percentile=False)  # no objective uses the percentile
            return objective_value(kpis, self.objective, self.sinr_weight)
        cols = torch.as_tensor(
            np.unique(np.concatenate([r.numpy() for p in positions if (r := self._rows[p]) is not None]))
        )
        before, after = [], []
        for g in sorted({int(self.group_of[p]) for p in positions}):
            rows = self.groups[g][1]
            known = self.known[torch.as_tensor(rows)[:, None], cols]  # [n_g, cols], without the other grids
            moved = [p for p in positions if int(self.group_of[p]) == g]
            keep = known.any(dim=1)  # cells heard at none of these grids add nothing there
            keep[torch.as_tensor([int(np.flatnonzero(rows == p)[0]) for p in moved])] = True
            idx = torch.nonzero(keep).reshape(-1)
            power = self.power[torch.as_tensor(rows)[idx][:, None], cols]  # [k, cols]
            known = known[idx]
            local = power.unsqueeze(0).repeat(n, 1, 1)  # [C, k, cols]
            for p in moved:
                local[:, int(torch.nonzero(idx == int(np.flatnonzero(rows == p)[0]))[0])] = cand[p][:, cols]
            before.append(carrier_samples(power, self.noise_mw[g], known, self.kpi))
            after.append(carrier_samples(local, self.noise_mw[g], known, self.kpi))
        old, new = objective_sums(before, self.kpi), objective_sums(after, self.kpi)
        delta = objective_value(
            {k: (new[k] - old[k]) / self._count for k in new} | {"num_samples": torch.full((n,), self._count)},
            self.objective,
            self.sinr_weight,
        )
        return self.score() + delta

    def set_cell(self, pos: int, index: tuple[int, ...], power: torch.Tensor | None = None) -> None:
        """Move cell ``pos`` to ``index`` (``power [num_grids]`` if already known)."""
        self.config[pos] = tuple(index)
        self.power[pos] = self._powers(pos, [tuple(index)])[0] if power is None else power
        g = int(self.group_of[pos])
        self._samples[g] = self._carrier(g, self.power[torch.as_tensor(self.groups[g][1])])
        self._score = None

    def set_config(self, config: Config) -> None:
        for pos, index in enumerate(config):
            if tuple(index) != self.config[pos]:
                self.set_cell(pos, index)

    def score(self) -> float:
        """Objective of the current configuration."""
        if self._score is None:
            self._score = float(objective_value(area_kpis(self._samples, self.kpi), self.objective, self.sinr_weight))
        return self._score

    def kpis(self) -> dict[str, Any]:
        """Network KPIs (pooled and per carrier) of the current configuration."""
        return network_kpis(
            self.power.double().numpy(), self.freqs, self.kpi, None if self.all_known else self.known_np
        )


def _expand(samples: dict[str, torch.Tensor], n: int) -> dict[str, torch.Tensor]:
    out = dict(samples)
    for key in ("best_mw", "sinr_lin", "overlap"):
        if out[key].dim() == 1:
            out[key] = out[key].unsqueeze(0).expand(n, -1)
    return out


@dataclass
class SearchResult:
    config: Config
    objective: float
    base_objective: float
    evaluations: int
    time_s: float
    method: str
    history: list[tuple[int, float, float]] = field(default_factory=list)
    """(evaluations, seconds, best objective) after each improvement."""


def _line(ev: NetworkEvaluator, pos: int, var: int) -> Config:
    """Candidates of cell ``pos`` along variable ``var`` that respect the changed-cells limit."""
    return [m[pos] for m in _moves(ev, pos, var)]


def _moves(ev: NetworkEvaluator, pos: int, var: int) -> list[dict[int, tuple[int, ...]]]:
    """Moves of cell ``pos`` along variable ``var`` (with the cells sharing its antenna panel when ``var`` is
    a panel's) that respect the total-tilt step and the changed-cells limit; the present state is one."""
    current = ev.config[pos]
    opts = ev.space.cells[pos]
    space = ev.space
    group = space.panel_of(pos) if VARIABLES[var] in SHARED_VARIABLES else (pos,)
    limit = space.max_changed_cells
    others = ev.num_changed() - sum(ev.config[p] != ev.base[p] for p in group)
    moves = []
    for k in range(opts.sizes()[var]):
        cand = (*current[:var], k, *current[var + 1 :])
        move = {pos: cand}
        for other in group:
            if other != pos:
                followed = space.follow(pos, cand, other, ev.config[other])
                if followed is None:
                    break
                move[other] = followed
        else:
            if not all(space.tilt_ok(p, i) for p, i in move.items()):
                continue
            if limit is not None and others + sum(i != ev.base[p] for p, i in move.items()) > limit:
                continue
            moves.append(move)
    return moves


def coordinate_descent(
    ev: NetworkEvaluator,
    restarts: int = 2,
    max_passes: int = 8,
    seed: int = 0,
    perturb_cells: int = 3,
    on_cell: Callable[[], None] | None = None,
) -> SearchResult:
    """Coordinate descent with restarts (the baseline).

    One pass visits every free cell and, per cell, every variable of :data:`VARIABLES`: all values of
    that variable are scored in one batch and the best is taken when it improves the objective.  Passes
    repeat until none improves (or ``max_passes``).  Restart r > 0 starts from the best configuration
    with ``perturb_cells`` random free cells set to random options (within the changed-cells limit),
    and visits cells in a random order.
    """
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    ev.set_config(ev.base)
    base_obj = best_obj = ev.score()
    best: Config = list(ev.config)
    history = [(ev.evaluations, 0.0, best_obj)]
    free = ev.space.free_cells()
    for restart in range(restarts + 1):
        ev.set_config(best)
        order = list(free)
        if restart:
            _perturb(ev, rng, free, perturb_cells)
            rng.shuffle(order)
        current = ev.score()
        for _ in range(max_passes):
            improved = False
            for pos in order:
                for var in range(len(VARIABLES)):
                    moves = _moves(ev, pos, var)
                    if len(moves) < 2:
                        continue
                    scores = ev.score_moves(moves)
                    k = int(torch.argmax(scores))
                    if float(scores[k]) > current + 1e-12 and any(i != ev.config[p] for p, i in moves[k].items()):
                        for p, i in moves[k].items():
                            ev.set_cell(p, i)
                        current, improved = ev.score(), True
                if on_cell is not None:
                    on_cell()
            if current > best_obj + 1e-12:
                best_obj, best = current, list(ev.config)
                history.append((ev.evaluations, time.perf_counter() - t0, best_obj))
            if not improved:
                break
    ev.set_config(best)
    return SearchResult(
        best,
        best_obj,
        base_obj,
        ev.evaluations,
        time.perf_counter() - t0,
        "coordinate-descent",
        history,
    )


def _perturb(ev: NetworkEvaluator, rng: np.random.Generator, free: list[int], n: int) -> None:
    limit = ev.space.max_changed_cells
    for pos in rng.permutation(free)[:n]:
        config = list(ev.config)
        config[int(pos)] = tuple(int(rng.integers(s)) for s in ev.space.cells[pos].sizes())
        config = ev.space.tie(config)
        if limit is not None and ev.num_changed(config) > limit:
            continue
        ev.set_config(config)


def differential_evolution(
    ev: NetworkEvaluator,
    time_budget_s: float = 60.0,
    seed: int = 0,
    popsize: int = 2,
    on_generation: Callable[[], None] | None = None,
) -> SearchResult:
    """scipy's differential evolution over the integer option indices of every free cell, seeded with
    the present configuration; configurations beyond the changed-cells limit are repaired by
    resetting the surplus changed cells (in cell order).  Stops after ``time_budget_s``."""
    from scipy.optimize import differential_evolution as scipy_de

    free = ev.space.free_cells()
    sizes = np.array([ev.space.cells[p].sizes() for p in free], dtype=np.float64)  # [free, 4]
    t0 = time.perf_counter()
    ev.set_config(ev.base)
    base_obj = ev.score()
    state: dict[str, Any] = {"best": base_obj, "config": list(ev.base)}
    history = [(ev.evaluations, 0.0, base_obj)]

    def decode(x: np.ndarray) -> Config:
        idx = np.clip(np.rint(x.reshape(len(free), 4)), 0, sizes - 1).astype(int)
        config = list(ev.base)
        changed = 0
        for p, row in zip(free, idx):
            cand = tuple(int(v) for v in row)
            if cand != ev.base[p] and (ev.space.max_changed_cells is None or changed < ev.space.max_changed_cells):
                config[p], changed = cand, changed + 1
        config = ev.space.tie(config)
        limit = ev.space.max_changed_cells
        for p in reversed(free):  # a panel that followed its lead may pass the limit: undo the last changes
            if limit is None or ev.num_changed(config) <= limit:
                break
            for q in ev.space.panel_of(p):
                config[q] = ev.base[q]
        return ev.space.tie(config)

    def fun(x: np.ndarray) -> float:
        config = decode(x)
        ev.set_config(config)
        value = ev.score()
        if value > state["best"] + 1e-12:
            state.update(best=value, config=list(config))
            history.append((ev.evaluations, time.perf_counter() - t0, value))
        return -value

    x0 = np.array([ev.base[p] for p in free], dtype=np.float64).reshape(-1)
    bounds = [(0.0, s - 1.0) for s in sizes.reshape(-1)]

    def stop(*_: object, **__: object) -> bool:
        if on_generation is not None:
            on_generation()
        return time.perf_counter() - t0 > time_budget_s

    scipy_de(
        fun,
        bounds,
        x0=x0,
        integrality=np.ones(len(bounds), dtype=bool),
        popsize=popsize,
        seed=seed,
        polish=False,
        maxiter=10**6,
        tol=0.0,
        callback=stop,
        init="latinhypercube",
    )
    ev.set_config(state["config"])
    return SearchResult(
        state["config"],
        state["best"],
        base_obj,
        ev.evaluations,
        time.perf_counter() - t0,
        "scipy-differential-evolution",
        history,
    )
