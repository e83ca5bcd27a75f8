"""Measure an existing trace again: another measurement regime without re-tracing (``rflscm simulate --from-trace``).

A simulated scenario keeps every traced path in ``truth/paths.parquet`` (per receiver point), so the
measurement step — samples, real antenna, fading, report error, reporting rule — can run again with
other settings.  Cells (both rounds), grids and the point cloud are copied unchanged; ``truth/`` and
the measurements are rewritten; ``scenario.yaml`` records the new settings under ``simulation``.
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from rflscm.config import from_dict, to_dict
from rflscm.data import load_scenario, read_table
from rflscm.errors import ConfigError, DataError
from rflscm.runtime import Mapper
from rflscm.sim.builder import SimulationConfig, write_measurements
from rflscm.sim.paths import PATHS_FILE
from rflscm.sim.stream import SpilledPaths

REMEASURE_STREAM = 2
"""Sub-stream of ``seed`` that draws the report error of a re-measured scenario (a new build draws it after
the layout, so a re-measured ideal scenario has other, equally distributed, noise)."""


def trace_config(source: str | Path) -> SimulationConfig:
    """The :class:`SimulationConfig` recorded in a simulated scenario's ``scenario.yaml``."""
    scenario = load_scenario(source, measurements=False)
    recorded = scenario.meta.simulation.get("config")
    if not isinstance(recorded, dict):
        raise DataError(
            f"{source}: scenario.yaml has no `simulation.config`; only `rflscm simulate` output can be re-measured."
        )
    return from_dict(SimulationConfig, recorded, prefix="simulation.config")


def remeasure(source: str | Path, config: SimulationConfig, out: str | Path, mapper: Mapper = map) -> Path:
    """Write a copy of the simulated scenario ``source`` into ``out`` measured with ``config``'s regime.

    Only the measurement keys of ``config`` may differ from the trace's own (``measurements``,
    ``field_model``, noise, threshold, ``detect_on``, ``seed``, ``name``, ``description``,
    ``truth_rsrp_margin_db``); a layout or tracing key that differs is a :class:`ConfigError`.
    """
    scenario = load_scenario(source, measurements=False)  # its measurements are replaced: never read
    traced = trace_config(source)
    allowed = {
        "measurements",
        "field_model",
        "noise_sigma_db",
        "quantization_db",
        "rsrp_threshold_dbm",
        "detect_on",
        "seed",
        "name",
        "description",
        "truth_rsrp_margin_db",
    }
    changed = [
        f.name
        for f in dataclasses.fields(SimulationConfig)
        if f.name not in allowed and to_dict(getattr(config, f.name)) != to_dict(getattr(traced, f.name))
    ]
    if changed:
        raise ConfigError(
            f"--from-trace re-measures the trace of {source}; these keys change the layout or the trace and need a new "
            f"simulation: {', '.join(changed)}."
        )
    if scenario.meta.truth is None:
        raise DataError(f"{source}: no truth folder, so no paths to measure.")
    paths = read_table(scenario.root / scenario.meta.truth / PATHS_FILE)
    paths = paths.astype({"power_lin": "float64", "aod_el_rad": "float64", "aod_az_rad": "float64"})
    paths["interactions"] = paths["interactions"].astype(str)
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise ConfigError(f"{out}: folder exists and is not empty; choose another --out or pass --force.")
    out.mkdir(parents=True, exist_ok=True)
    simulation: dict[str, Any] = dict(scenario.meta.simulation)
    simulation.update(
        measurements=config.measurements,
        remeasured_from=str(scenario.meta.name),
        seed=config.seed,
        config=to_dict(config),
        noise={
            "sigma_db": config.noise_sigma_db,
            "quantization_db": config.quantization_db,
            "threshold_dbm": config.rsrp_threshold_dbm,
        },
    )
    simulation.pop("field", None)
    if config.measurements == "field":
        simulation["field"] = to_dict(config.field_model)
    meta = dataclasses.replace(
        scenario.meta,
        name=config.name,
        description=config.description or scenario.meta.description,
        rsrp_threshold_dbm=config.threshold_dbm,
        reporting={},
        simulation=simulation,
    )
    fresh = dataclasses.replace(scenario, root=out.resolve(), meta=meta)
    rng = np.random.default_rng([config.seed, REMEASURE_STREAM])
    store = SpilledPaths(out / ".trace")  # one (site, carrier) in memory at a time, in the trace's order
    try:
        for (site, freq), group in paths.groupby(["site_id", "freq_hz"], sort=False):
            store.add(int(site), float(freq), group)
        del paths
        (out / "truth").mkdir(parents=True, exist_ok=True)
        shutil.copyfile(scenario.root / scenario.meta.truth / PATHS_FILE, out / "truth" / PATHS_FILE)  # the trace
        write_measurements(fresh, store, config, rng, out, paths_written=True, mapper=mapper)
    finally:
        store.remove()
    return load_scenario(out).root
