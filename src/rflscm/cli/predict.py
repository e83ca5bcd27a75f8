"""``rflscm predict``: RSRP under any antenna configuration, APS export, attenuation map."""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
import typer
from rich.console import Console

from rflscm.cli import app
from rflscm.cli.common import (
    SEED_MAX,
    Device,
    DeviceOption,
    ForceOption,
    SeedOption,
    check_numbers,
    json_text,
    resolve_device,
    seed_everything,
)
from rflscm.errors import ConfigError, RflscmError
from rflscm.geometry.angles import internal_to_engineering
from rflscm.parallel import Engine, RayAddressOption, WorkersOption

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario
    from rflscm.models.base import LSCMModel


class Pairs(StrEnum):
    measured = "measured"
    all = "all"


def _id_list(text: str | None, option: str) -> np.ndarray | None:
    if text is None:
        return None
    try:
        return np.array([int(v) for v in text.split(",") if v.strip()], dtype=np.int64)
    except (ValueError, OverflowError):
        raise ConfigError(f"{option} takes comma-separated integer ids (got {text!r}).") from None


def prediction_pairs(scenario: Scenario, model, which: str) -> pd.DataFrame:
    """(cell_id, grid_id) pairs to predict: ``measured`` (any round) or ``all`` (every cell × grid)."""
    if which == "all":
        if not model.supports_unseen_grids:
            raise ConfigError(f"{model.name} has no notion of unseen grids; use --pairs measured.")
        cells, grids = np.meshgrid(scenario.cell_ids(), scenario.grid_ids(), indexing="ij")
        return pd.DataFrame({"cell_id": cells.ravel(), "grid_id": grids.ravel()})
    if which != "measured":
        raise ConfigError(f"--pairs must be measured or all (got {which!r}).")
    m = scenario.measurements
    if not model.supports_unseen_grids:  # only the pairs the model was fitted on
        m = m[m["round"] == 1]
    return m[["cell_id", "grid_id"]].drop_duplicates().sort_values(["cell_id", "grid_id"]).reset_index(drop=True)


def long_form(round: int, beam_type: str, pairs: pd.DataFrame, rsrp_dbm: np.ndarray, scenario) -> pd.DataFrame:
    """Long-form prediction rows (the measurement table's layout) for one beam type."""
    num_beams = np.array([scenario.num_beams(c, beam_type, round) for c in pairs["cell_id"]])
    beam = np.arange(rsrp_dbm.shape[1])
    keep = beam[None, :] < num_beams[:, None]
    rows, beams = np.nonzero(keep)
    return pd.DataFrame(
        {
            "round": round,
            "cell_id": pairs["cell_id"].to_numpy()[rows],
            "grid_id": pairs["grid_id"].to_numpy()[rows],
            "beam_type": beam_type,
            "beam_id": beams,
            "rsrp_dbm": rsrp_dbm[rows, beams],
        }
    )


def _check_aps_ids(scenario: Scenario, cells: np.ndarray, grids: np.ndarray) -> None:
    """``--aps-cells`` / ``--aps-grids`` name known ids (checked before any prediction is made)."""
    options = (("--aps-cells", cells, scenario.cell_ids()), ("--aps-grids", grids, scenario.grid_ids()))
    for option, ids, known in options:
        unknown = np.setdiff1d(ids, known)
        if unknown.size or not ids.size:
            shown = ", ".join(map(str, known[:10])) + (", …" if len(known) > 10 else "")
            what = f"has unknown id(s) {', '.join(map(str, unknown[:5]))}" if unknown.size else "is empty"
            raise ConfigError(f"{option} {what}; ids of scenario {scenario.meta.name!r}: {shown}.")


def _export_aps(model: LSCMModel, scenario: Scenario, cells: np.ndarray, grids: np.ndarray, path: Path) -> int:
    _check_aps_ids(scenario, cells, grids)
    cell_ids, grid_ids = (a.ravel() for a in np.meshgrid(cells, grids, indexing="ij"))
    xyz = scenario.grids.set_index("grid_id").loc[grid_ids, ["x", "y", "z"]].to_numpy()
    aps = model.checked_aps(cell_ids, grid_ids, xyz, scenario).detach().cpu().double().numpy()
    pair, bins = np.nonzero(aps > 0)
    el, az = model.angle_grid.bin_angles()
    azimuth_deg, _ = internal_to_engineering(el, az)
    table = pd.DataFrame(
        {
            "cell_id": cell_ids[pair],
            "grid_id": grid_ids[pair],
            "bin": bins.astype(np.int32),
            "elevation_deg": np.rad2deg(el[bins]),
            "azimuth_deg": azimuth_deg[bins],  # clockwise from north, as the cells tables
            "power_lin": aps[pair, bins],
        }
    )
    from rflscm.data import write_table

    write_table(table, path)
    return len(table)


def _print_kpis(
    scen, model, selected: pd.DataFrame, ssb: pd.DataFrame, threshold: float, path: Path | None, console: Console
) -> None:
    """Network KPIs (rflscm.network) of the predicted SSB RSRP, printed and optionally written as JSON."""

    from rflscm.network.kpi import KPIConfig, best_beam_power_from_rsrp, network_kpis

    wide = ssb.pivot_table(index=["cell_id", "grid_id"], columns="beam_id", values="rsrp_dbm", aggfunc="first")
    cells, grids = wide.index.get_level_values(0).to_numpy(), wide.index.get_level_values(1).to_numpy()
    power, known = best_beam_power_from_rsrp(wide.to_numpy(), cells, grids, scen.cell_ids(), scen.grid_ids())
    freqs = np.array([scen.freq_hz(int(c)) for c in scen.cell_ids()])
    kpis = network_kpis(power, freqs, KPIConfig(threshold_dbm=threshold), None if known.all() else known)
    kpis["pairs"] = "every (cell, grid) pair" if known.all() else f"{int(known.sum())} (cell, grid) pairs only"
    if path is not None:
        from rflscm.data.safe_io import write_text_atomic

        write_text_atomic(path, json_text(kpis), "KPI JSON")
    console.print(
        f"network KPIs on {kpis['pairs']}: coverage {100 * kpis['coverage']:.2f} %, mean SS-SINR "
        f"{kpis['mean_sinr_db']:.2f} dB, 5th percentile SS-SINR {kpis['p5_sinr_db']:.2f} dB, overlap "
        f"{100 * kpis['overlap']:.2f} %, mean best-server RSRP {kpis['mean_rsrp_dbm']:.2f} dBm "
        f"(--pairs {'measured' if not known.all() else 'all'}; `rflscm optimize` reports the same KPIs "
        "on the same pairs)"
    )


@app.command()
def predict(
    checkpoint: Path = typer.Argument(..., help="Model checkpoint written by `rflscm train`."),
    scenario: Path = typer.Argument(
        ..., help="The scenario the model was trained on; its rounds are the antenna configurations."
    ),
    round: int = typer.Option(
        2,
        "--round",
        help="Round to predict (integer; its antenna configuration); add a round to scenario.yaml for a what-if.",
    ),
    out: Path = typer.Option(
        Path("prediction.parquet"),
        "--out",
        help="Predicted RSRP table (.parquet or .csv); grid x/y (m) and, with an origin, lat/lon (deg) beside grid ids.",
    ),
    pairs_choice: Pairs = typer.Option(
        Pairs.measured, "--pairs", help="measured: pairs with measurements; all: every cell × grid."
    ),
    aps_cells: str | None = typer.Option(None, "--aps-cells", help="Comma-separated cell ids whose APS to export."),
    aps_grids: str | None = typer.Option(None, "--aps-grids", help="Comma-separated grid ids whose APS to export."),
    aps_out: Path = typer.Option(Path("aps.parquet"), "--aps-out", help="Where the exported APS goes."),
    attenuation_map: Path | None = typer.Option(
        None,
        "--attenuation-map",
        help="PNG map of the learned attenuation −log|δ| over the scene, seen from above (rflscm and nerf2 only).",
    ),
    kpi: bool = typer.Option(
        False,
        "--kpi",
        help="Also print network KPIs of the round (coverage and overlap in %, SS-SINR in dB) on the predicted pairs.",
    ),
    kpi_json: Path | None = typer.Option(
        None, "--kpi-json", help="Write the network KPIs as JSON here (implies --kpi)."
    ),
    threshold: float = typer.Option(-105.0, "--threshold", help="--kpi: coverage threshold on best-server RSRP (dBm)."),
    device: Device = DeviceOption,
    seed: int = SeedOption,
    workers: int = WorkersOption,
    ray_address: str | None = RayAddressOption,
    force: bool = ForceOption,
) -> None:
    """Predict RSRP of every beam for a round's antenna configuration (also for grids without measurements)."""
    pairs = pairs_choice.value
    from rflscm.data import load_scenario, write_table
    from rflscm.data.io import table_kind
    from rflscm.data.loader import scenario_inputs
    from rflscm.data.safe_io import guard_outputs
    from rflscm.models import load_model
    from rflscm.parallel.aps import checkpoint_loader, prediction_cache

    check_numbers(round=(round, 1, 2**31 - 1), threshold=(threshold, -300.0, 100.0), seed=(seed, 0, SEED_MAX))
    cells, grids = _id_list(aps_cells, "--aps-cells"), _id_list(aps_grids, "--aps-grids")
    if (cells is None) != (grids is None):
        raise ConfigError("--aps-cells and --aps-grids go together.")
    for option, path, suffixes in (
        ("--out", out, None),
        ("--aps-out", aps_out if cells is not None else None, None),
        ("--attenuation-map", attenuation_map, (".png",)),
        ("--kpi-json", kpi_json, (".json",)),
    ):
        if path is None:
            continue
        if suffixes is None:
            try:
                table_kind(path)
            except RflscmError:
                raise ConfigError(f"{option} {path}: unknown table format; use .parquet or .csv.") from None
        elif path.suffix.lower() not in suffixes:
            raise ConfigError(f"{option} {path}: the file name must end in {' or '.join(suffixes)}.")
    outputs = {
        "--out": out,
        "--aps-out": aps_out if cells is not None else None,
        "--attenuation-map": attenuation_map,
        "--kpi-json": kpi_json,
    }
    guard_outputs(outputs, [*scenario_inputs(scenario), checkpoint], force=force)
    seed_everything(seed)
    dev = resolve_device(device)
    console = Console(stderr=True)
    scen = load_scenario(scenario)
    if round not in scen.cells:
        raise ConfigError(
            f"--round {round}: scenario {scen.meta.name!r} has rounds {', '.join(map(str, scen.rounds()))}."
        )
    if cells is not None and grids is not None:
        _check_aps_ids(scen, cells, grids)
    model = load_model(checkpoint, scen, device=dev)
    if attenuation_map is not None and not hasattr(model, "all_stages"):
        raise ConfigError(f"{model.name} has no attenuation field; --attenuation-map needs an rflscm or nerf2 model.")
    selected = prediction_pairs(scen, model, pairs)
    engine = Engine(workers, ray_address)  # > 1 worker: the APS of the pairs are computed by Ray workers first
    cached = prediction_cache(model, scen, selected, engine, checkpoint_loader(checkpoint, scenario, dev))
    if engine.parallel:
        console.print(f"{cached.filled} (cell, grid) pairs' APS computed by {workers} Ray worker(s)")
    with console.status(f"predicting {len(selected)} (cell, grid) pairs with {model.name}…"):
        tables = [
            long_form(round, bt, selected, cached.predict_rsrp(scen, round, bt, selected), scen)
            for bt in ("ssb", "csi")
        ]
    out.parent.mkdir(parents=True, exist_ok=True)
    from rflscm.maps.vector import with_grid_positions

    write_table(with_grid_positions(pd.concat(tables, ignore_index=True), scen), out)  # x/y (lat/lon) beside grid_id
    console.print(f"wrote {out} ({sum(len(t) for t in tables)} beams)")
    if kpi or kpi_json is not None:
        _print_kpis(scen, model, selected, tables[0], threshold, kpi_json, console)
    if cells is not None and grids is not None:
        n = _export_aps(model, scen, cells, grids, aps_out)
        console.print(f"wrote {aps_out} ({n} non-zero bins)")
    if attenuation_map is not None:
        from rflscm.eval.report import write_attenuation_map

        write_attenuation_map(model, scen, attenuation_map, round)
        console.print(f"wrote {attenuation_map}")
