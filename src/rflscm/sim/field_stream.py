"""The field regime, one cell at a time (issue 29): what :func:`rflscm.sim.field.field_rsrp` →
:func:`rflscm.sim.field.report` → :func:`rflscm.sim.paths.write_truth` and the samples' truth wrote on long tables
(``tests/unit/sim/test_field_stream.py`` keeps that path as its reference), without the long tables.

The whole-table path builds the RSRP of every (round, cell, grid, beam) twice (faded and fading-free) as long
tables before it reports: 2 × rounds × cells × grids × 40 rows, 8–24 GB at 222 cells (1 300–4 229 grids) and
beyond this machine at 1 002.
Here each round is measured cell by cell, in the whole table's order:

1. the faded and the fading-free RSRP of a cell (``[grids, beams]`` per beam type, the same sample sums, real
   antennas and random draws as :func:`~rflscm.sim.field.field_rsrp`); its report error drawn from ``rng`` block
   by block in table order (the same numbers as one draw over the table); its truth rows appended to
   ``truth/rsrp_noiseless.parquet``; what the later steps need kept: the SSB power of every grid (the
   interference of SS-SINR detection, summed per carrier) and the reported values of the grids where one of its
   SSB beams passed the threshold (no other grid can be detected);
2. SS-SINR detection, SSB top-N and detection per (cell, grid), the serving cell of each (carrier, grid);
3. the serving cells' CSI-RS and its top-N; the rows appended to the measurements file.

Drive routes are drawn from ``rng`` after every report error, as the whole-table path draws them: a copy of the
generator is advanced by the same draws first.  ``truth/aps_samples.parquet`` is written round by round and
cell by cell.  Memory: per round one SSB power array of the network (cells × grids × 8, float64) and the
reported values of the grids a cell reaches; no long table.  ``tests/unit/sim/test_field_stream.py`` compares
every file with the whole-table path's.
"""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from rflscm.data import BEAM_TYPES
from rflscm.geometry import AngleGrid
from rflscm.sim.field import (
    FieldConfig,
    SampleSums,
    _no_channel_effects,
    array_errors,
    draw_samples,
    drive_route,
    path_beam_power,
)
from rflscm.sim.paths import APS_FILE, RSRP_FILE, bin_paths, cell_rsrp_dbm, to_dbm
from rflscm.sim.stream import (
    ParquetAppender,
    PathStore,
    _measurement_frame,
    empty_truth_rsrp,
    long_rows,
    truth_rsrp_frame,
    write_aps_streamed,
)

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario

SSB, CSI = BEAM_TYPES
_SUM_COLUMNS = 4096  # (grid, beam) groups summed at once: 2 × cells × this many values in memory


@dataclasses.dataclass
class _Reported:
    """One (round, cell)'s reports at the grids where an SSB beam passed the threshold: grid positions
    ``[n]`` and the reported SSB / CSI-RS values ``[n, beams]`` (NaN: not reported), plus the SSB power [mW] of
    those grids as the whole-table path computes it from the dBm values (SS-SINR's numerator)."""

    cell_id: int
    carrier: int
    rows: np.ndarray
    ssb: np.ndarray
    csi: np.ndarray
    ssb_mw: np.ndarray


def _ssb_mw(rsrp_dbm: np.ndarray) -> np.ndarray:
    """Linear SSB power [mW] of dBm values, 0 where −inf (as :func:`~rflscm.sim.field.report` computes it)."""
    with np.errstate(divide="ignore"):
        return np.where(np.isfinite(rsrp_dbm), 10.0 ** (rsrp_dbm / 10.0), 0.0)


def _keep_top(values: np.ndarray, top_n: int) -> np.ndarray:
    """``values [n, beams]`` with every value outside the ``top_n`` largest of its row set to NaN (ties: the
    lower beam first, as pandas' ``rank(method="first")`` over the table's order)."""
    if values.shape[1] <= top_n:
        return values
    order = np.argsort(-np.nan_to_num(values, nan=-np.inf), axis=1, kind="stable")
    keep = np.zeros(values.shape, dtype=bool)
    np.put_along_axis(keep, order[:, :top_n], True, axis=1)
    return np.where(keep, values, np.nan)


def _sum_in_table_order(stack: np.ndarray) -> np.ndarray:
    """Σ over axis 0 of ``stack [cells, grids, beams]`` as pandas' grouped sum adds the long table's rows of a
    (grid, beam id): cell after cell, each cell's SSB value followed by the 0 of its CSI-RS row of that beam id
    (the table's CSI-RS rows carry no SSB power but share the group), with pandas' compensated summation, so that
    SS-SINR is the whole-table path's to the bit."""
    cells = stack.shape[0]
    values = stack.reshape(cells, -1)
    out = np.empty(values.shape[1])
    for start in range(0, values.shape[1], _SUM_COLUMNS):  # groups are independent: a block at a time
        block = values[:, start : start + _SUM_COLUMNS]
        flat = np.zeros((2 * cells, block.shape[1]))
        flat[0::2] = block
        labels = np.tile(np.arange(block.shape[1]), 2 * cells)
        out[start : start + block.shape[1]] = pd.Series(flat.reshape(-1)).groupby(labels, sort=True).sum().to_numpy()
    return out.reshape(stack.shape[1:])


def _group(store: PathStore, key: tuple[int, float]) -> pd.DataFrame:
    """The paths of a traced (site, carrier); every key asked for here is one of the store's."""
    paths = store.group(key)
    if paths is None:
        raise KeyError(f"no paths for (site, carrier) {key}")
    return paths


class _CellRsrp:
    """The faded and fading-free RSRP [dBm] ``[grids, beams]`` of a (round, cell, beam type), from one round's
    sample sums (built for every traced (site, carrier) in the whole-table path's order, drawing its phases)."""

    def __init__(
        self,
        scenario: Scenario,
        store: PathStore,
        keys: list[tuple[int, float]],
        grid_ids: np.ndarray,
        points_per_grid: int,
        config: FieldConfig,
        samples: pd.DataFrame,
        rng: np.random.Generator,
        gains: dict[int, Any],
        element: Any,
        rnd: int,
    ) -> None:
        self.scenario, self.store, self.grid_ids = scenario, store, grid_ids
        self.config, self.gains, self.element, self.rnd = config, gains, element, rnd
        self.exact = _no_channel_effects(config)
        self.sums: dict[tuple[int, float], SampleSums] = {}
        if not self.exact:
            in_round = samples[samples["round"] == rnd]
            for key in keys:
                self.sums[key] = SampleSums(_group(store, key), grid_ids, in_round, config, rng)
        self.keys = set(keys)
        self.counts = pd.Series(points_per_grid, index=grid_ids)

    def __call__(self, cell_id: int, beam_type: str) -> tuple[np.ndarray, np.ndarray]:
        sc, rnd = self.scenario, self.rnd
        row = sc.cell_row(cell_id, rnd)
        key = (int(row["site_id"]), float(row["freq_hz"]))
        book = sc.codebook(cell_id, beam_type, rnd)
        if key not in self.keys:
            none = np.full((len(self.grid_ids), book.num_beams), -np.inf)
            return none, none
        paths = _group(self.store, key)
        if self.exact:
            exact = cell_rsrp_dbm(sc, cell_id, beam_type, rnd, paths, self.grid_ids, self.counts)
            return exact, exact
        antenna = sc.antenna(cell_id, rnd)
        if self.element is not None:
            antenna = dataclasses.replace(antenna, element=self.element)
        q = path_beam_power(paths, antenna, book, sc.wavelength_m(cell_id), self.gains[cell_id])
        mean = self.sums[key].mean @ q
        faded = self.sums[key].faded(q) if self.config.fading else mean
        return to_dbm(faded), to_dbm(mean)


def stream_field(
    scenario: Scenario,
    store: PathStore,
    points_per_grid: int,
    config: FieldConfig,
    field_rng: np.random.Generator,
    rng: np.random.Generator,
    truth: Path,
    rsrp_floor_dbm: float | None,
    angle_grid: AngleGrid,
    measurements_file: Path,
) -> None:
    """The field regime's measurements (appended to ``measurements_file``) and ``truth/`` (APS, noiseless RSRP,
    samples and their APS), cell by cell; ``field_rng`` draws samples, array errors and phases, ``rng`` the report
    error and the drive routes, as in the whole-table path.  ``truth/paths.parquet`` is not written here."""
    from rflscm.data import empty_measurements

    grid_ids = np.asarray(scenario.grid_ids())
    counts = pd.Series(points_per_grid, index=grid_ids)
    truth.mkdir(parents=True, exist_ok=True)
    write_aps_streamed(truth / APS_FILE, scenario, store, angle_grid, counts)
    rounds = scenario.rounds()
    samples = draw_samples(grid_ids, points_per_grid, config, rounds, field_rng)
    gains: dict[int, Any] = {}
    element = None
    if not _no_channel_effects(config):
        if config.real_element is not None:
            from rflscm.antenna import read_msi

            element = read_msi(config.real_element)
        for cell_id in scenario.cell_ids():  # fixed per cell: drawn once, in cell order
            array = scenario.antenna(int(cell_id), 1).array
            gains[int(cell_id)] = array_errors(array.num_h, array.num_v, config, field_rng)
    keys = sorted(k for k in store.group_keys() if len(_group(store, k)) > 0)  # traced, with a path
    route = _drive_route(scenario, config, rng) if config.drive_routes > 0 else None
    model = config.measurement_model
    freq_of = scenario.cells[1].set_index("cell_id")["freq_hz"]  # the carrier groups of SS-SINR, as report's
    carriers = sorted({float(f) for f in freq_of})
    with (
        ParquetAppender(truth / RSRP_FILE, empty_truth_rsrp()) as rsrp_file,
        ParquetAppender(measurements_file, empty_measurements(), page_checksum=True) as sink,
    ):
        for rnd in rounds:
            rsrp = _CellRsrp(
                scenario, store, keys, grid_ids, points_per_grid, config, samples, field_rng, gains, element, rnd
            )
            cells = [int(c) for c in scenario.cell_ids()]
            carrier_of = {c: carriers.index(float(freq_of[c])) for c in cells}
            num_ssb = max(scenario.codebook(c, SSB, rnd).num_beams for c in cells)
            ssb_power = np.zeros((len(cells), len(grid_ids), num_ssb))
            reported: list[_Reported] = []
            for i, cell_id in enumerate(cells):
                measured, expected = {}, {}
                for beam_type in BEAM_TYPES:
                    measured[beam_type], expected[beam_type] = rsrp(cell_id, beam_type)
                noisy = {bt: model.apply(measured[bt], rng) for bt in BEAM_TYPES}  # draws in table order
                _append_truth(rsrp_file, rnd, cell_id, grid_ids, expected, rsrp_floor_dbm)
                ssb_power[i, :, : measured[SSB].shape[1]] = _ssb_mw(measured[SSB])
                heard = np.flatnonzero(~np.isnan(noisy[SSB]).all(axis=1))
                lin = ssb_power[i, heard, : measured[SSB].shape[1]]
                reported.append(
                    _Reported(cell_id, carrier_of[cell_id], heard, noisy[SSB][heard], noisy[CSI][heard], lin)
                )
            _report_round(rnd, reported, ssb_power, carrier_of, cells, grid_ids, config, route, sink)
            del rsrp, reported, ssb_power  # this round's sample sums go before the next round's are drawn
    _write_sample_truth(truth, scenario, store, keys, samples, points_per_grid, angle_grid)


def _report_round(
    rnd: int,
    reported: list[_Reported],
    ssb_power: np.ndarray,
    carrier_of: dict[int, int],
    cells: list[int],
    grid_ids: np.ndarray,
    config: FieldConfig,
    route: np.ndarray | None,
    sink: ParquetAppender,
) -> None:
    """SS-SINR detection, SSB top-N, detection, serving cells, CSI-RS rules and drive routes of one round's
    reports (steps 2 and 3), appended to ``sink`` in table order."""
    if config.ssb_detection == "sinr":
        noise_mw = 10.0 ** (config.noise_dbm / 10.0)
        carrier = np.array([carrier_of[c] for c in cells])
        total = {f: _sum_in_table_order(ssb_power[carrier == f]) for f in np.unique(carrier)}  # [grids, beams]
        for r in reported:
            lin = r.ssb_mw
            interference = total[r.carrier][r.rows, : lin.shape[1]] - lin + noise_mw
            sinr_db = 10.0 * np.log10(np.maximum(lin, 1e-300) / interference)
            r.ssb = np.where(sinr_db < config.ssb_sinr_db, np.nan, r.ssb)
    best = {f: np.full(len(grid_ids), -np.inf) for f in set(carrier_of.values())}
    serving = {f: np.full(len(grid_ids), -1, dtype=np.int64) for f in set(carrier_of.values())}
    for r in reported:
        if config.ssb_top_n is not None:
            r.ssb = _keep_top(r.ssb, config.ssb_top_n)
        detected = ~np.isnan(r.ssb).all(axis=1)
        r.rows, r.ssb, r.csi = r.rows[detected], r.ssb[detected], r.csi[detected]
        strongest = np.nanmax(r.ssb, axis=1) if len(r.rows) else np.zeros(0)
        better = strongest > best[r.carrier][r.rows]  # ties keep the lower cell id, as the whole-table sort
        best[r.carrier][r.rows[better]] = strongest[better]
        serving[r.carrier][r.rows[better]] = r.cell_id
    for r in reported:
        if not len(r.rows):
            continue
        grids, csi = grid_ids[r.rows], r.csi
        if config.csi_serving_only:
            mine = serving[r.carrier][r.rows] == r.cell_id
            csi_grids, csi = grids[mine], csi[mine]
        else:
            csi_grids = grids
        if config.csi_top_n is not None:
            csi = _keep_top(csi, config.csi_top_n)
        block = long_rows(rnd, r.cell_id, [(grids, r.ssb), (csi_grids, csi)])
        if route is not None:
            on_route = np.isin(block["grid_id"], route)
            block = {k: v[on_route] for k, v in block.items()}
        sink.append(_measurement_frame([block]))


def _append_truth(
    out: ParquetAppender,
    rnd: int,
    cell_id: int,
    grid_ids: np.ndarray,
    expected: dict[str, np.ndarray],
    floor_dbm: float | None,
) -> None:
    """The (round, cell)'s rows of ``truth/rsrp_noiseless.parquet``, without the grids whose strongest beam is
    below ``floor_dbm``."""
    keep = np.ones(len(grid_ids), dtype=bool)
    if floor_dbm is not None:
        keep = np.maximum(expected[SSB].max(axis=1), expected[CSI].max(axis=1)) >= floor_dbm
    if keep.any():
        out.append(
            truth_rsrp_frame(long_rows(rnd, cell_id, [(grid_ids[keep], expected[bt][keep]) for bt in BEAM_TYPES]))
        )


def _drive_route(scenario: Scenario, config: FieldConfig, rng: np.random.Generator) -> np.ndarray:
    """The drive routes the whole-table path draws after every report error: from a copy of ``rng`` advanced by
    the same report-error draws (one normal per row of every (round, cell, beam type) block, in order)."""
    ahead = copy.deepcopy(rng)
    if config.measurement_model.sigma_db > 0:
        num_grids = len(scenario.grids)
        for rnd in scenario.rounds():
            for cell_id in scenario.cell_ids():
                for beam_type in BEAM_TYPES:
                    ahead.normal(0.0, 1.0, (num_grids, scenario.codebook(int(cell_id), beam_type, rnd).num_beams))
    return drive_route(scenario.grids, config.drive_routes, config.drive_route_grids, ahead)


def _write_sample_truth(
    folder: Path,
    scenario: Scenario,
    store: PathStore,
    keys: list[tuple[int, float]],
    samples: pd.DataFrame,
    points_per_grid: int,
    angle_grid: AngleGrid,
) -> None:
    """``truth/samples.parquet`` (the UE samples of every round) and ``truth/aps_samples.parquet`` (the true APS of
    each round's samples, the model floor of ``rflscm evaluate``), the APS round by round and cell by cell."""
    samples.astype({"round": "int8", "grid_id": "int32", "point_id": "int16", "weight": "float32"}).to_parquet(
        folder / "samples.parquet", index=False, compression="zstd"
    )
    empty = pd.DataFrame(
        {
            "round": pd.Series(dtype="int8"),
            "cell_id": pd.Series(dtype="int32"),
            "grid_id": pd.Series(dtype="int32"),
            "bin": pd.Series(dtype="int32"),
            "power_lin": pd.Series(dtype="float32"),
        }
    )
    traced = set(keys)
    with ParquetAppender(folder / "aps_samples.parquet", empty) as out:
        for rnd, sub in samples.groupby("round"):
            index = pd.MultiIndex.from_frame(sub[["grid_id", "point_id"]])
            weight = pd.Series(sub["weight"].to_numpy(), index=index)
            binned: tuple[tuple[int, float], pd.DataFrame | None] | None = None
            cells = scenario.cells[1].sort_values("cell_id")
            for cell_id, site, freq in cells[["cell_id", "site_id", "freq_hz"]].itertuples(index=False):
                key = (int(site), float(freq))
                if key not in traced:
                    continue
                if binned is None or binned[0] != key:
                    paths = _group(store, key)
                    w = weight.reindex(pd.MultiIndex.from_frame(paths[["grid_id", "point_id"]].astype("int64")))
                    power = paths["power_lin"].to_numpy() * w.fillna(0.0).to_numpy() * points_per_grid
                    weighted = paths.assign(power_lin=power)
                    weighted = weighted[weighted["power_lin"] > 0]
                    binned = (key, bin_paths(weighted, angle_grid, points_per_grid) if len(weighted) else None)
                aps = binned[1]
                if aps is None:
                    continue
                out.append(
                    pd.DataFrame(
                        {
                            "round": np.full(len(aps), rnd, dtype=np.int8),
                            "cell_id": np.full(len(aps), cell_id, dtype=np.int32),
                            "grid_id": aps["grid_id"].to_numpy().astype(np.int32),
                            "bin": aps["bin"].to_numpy(np.int32),
                            "power_lin": aps["power_lin"].to_numpy().astype(np.float32),
                        }
                    )
                )
