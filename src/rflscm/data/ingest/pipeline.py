"""``rflscm import`` end to end: spec → cell list, samples → resolved, binned → a checked scenario folder."""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd
import yaml

from rflscm.config import from_dict, to_dict
from rflscm.data.cells import CELL_COLUMNS
from rflscm.data.geo import Origin
from rflscm.data.ingest.binning import bin_samples, grids_of, keep_top_n
from rflscm.data.ingest.cellist import NO_PCI, cell_origin, cells_frame, copy_elements, read_cell_list
from rflscm.data.ingest.cloud import check_cloud_frame
from rflscm.data.ingest.ground import cells_on_ground, read_terrain, samples_on_ground
from rflscm.data.ingest.resolve import resolve_cells
from rflscm.data.ingest.samples import Tally, read_samples
from rflscm.data.ingest.spec import ImportSpec
from rflscm.data.io import write_table
from rflscm.data.meta import RSRP_MIN_DBM, ScenarioMeta, meta_from_dict
from rflscm.data.pointcloud import PointCloud, read_point_cloud
from rflscm.data.reporting import BEAM_TYPES, reporting_from_dict
from rflscm.errors import DataError

DEFAULT_THRESHOLD_DBM = -120.0
"""rsrp_threshold_dbm without one given: this, or the weakest kept bin rounded down when that is lower (a low
threshold claims little about missing beams; a high one would claim they were all weaker than it)."""
BINS_FILE = "import_bins"
"""Side table of every kept bin: key, ``samples`` and ``std_db`` (the spread of its samples [dB])."""
CELL_MAP_FILE = "import_cells"
"""Side table: ``cell_id`` → the cell list's name, PCI and carrier."""


@dataclass
class ImportResult:
    """What an import kept and dropped."""

    samples_read: int = 0
    samples_kept: int = 0
    bins: int = 0
    grids: int = 0
    cells: int = 0
    rounds: list[int] = field(default_factory=list)
    threshold_dbm: float = -120.0
    threshold_chosen: bool = False
    origin: Origin | None = None
    dropped: Tally = field(default_factory=Tally)
    bins_table: pd.DataFrame | None = None
    point_cloud_points: int = 0


def import_raw(spec: ImportSpec, out: Path, table_format: str = "parquet") -> ImportResult:
    """Import ``spec``'s raw samples and cell list into scenario folder ``out`` (created; must not hold one).

    Raises:
        DataError / ConfigError: a file, row or value that cannot be used (one line naming it).
    """
    res = ImportResult()
    cloud = None if spec.point_cloud is None else _read_cloud(spec.point_cloud)  # refused before any work
    tables, _ = read_cell_list(spec)
    origin = from_dict(Origin, spec.origin, prefix="origin") if spec.origin is not None else cell_origin(tables)
    res.origin = origin
    terrain = None if spec.terrain is None else read_terrain(spec.terrain, origin)
    ids: dict[str, int] = {}
    cells = {r: cells_frame(df, origin, ids) for r, df in sorted(tables.items())}
    folders = {r: str(df.attrs.get("folder", ".")) for r, df in tables.items()}
    if 0 in cells and "round" in cells[0].columns:  # one table with a round column
        whole = cells.pop(0)
        for rnd, part in whole.groupby("round", sort=True):
            cells[int(rnd)] = part.drop(columns="round").reset_index(drop=True)
            folders[int(rnd)] = folders[0]
    samples = read_samples(spec, origin, res.dropped)
    res.samples_read = len(samples) + res.dropped.dropped
    if terrain is not None:
        name = {r: Path(spec.cells.get(r) or spec.cells.get(0) or "cells").name for r in cells}
        cells = {r: cells_on_ground(t, terrain, origin, name[r]) for r, t in cells.items()}
        samples = samples_on_ground(samples, terrain, origin, res.dropped)
    if 0 in cells:
        rounds = sorted(int(r) for r in samples["round"].unique()) or [1]
        cells = {r: cells[0] for r in rounds}
        folders = {r: folders[0] for r in rounds}
    else:
        orphan = ~samples["round"].isin(list(cells)).to_numpy()
        res.dropped.drop("round with no cell list", int(orphan.sum()))
        samples = samples[~orphan]
    if 1 not in cells:
        raise DataError(f"import: the samples and cell list give rounds {sorted(cells)}; round 1 is required.")
    by_pci = (samples["pci"] >= 0).to_numpy()
    if by_pci.any() and all((c["pci"] == NO_PCI).all() for c in cells.values()):
        row = samples[by_pci].iloc[0]
        raise DataError(
            f"{row['file']} row {row['row']}: names its cell by `pci` = {row['pci']}, but the cell list has no `pci` "
            "column; add it (map yours with --col cells.pci=NAME) or give the samples a `cell_id` column."
        )
    samples = resolve_cells(samples, cells, ids, spec, res.dropped)
    meta_dict = _meta_dict(spec, cells, origin)
    meta = meta_from_dict(meta_dict, "import spec")
    _check_beams(samples, cells, meta)
    rules = reporting_from_dict(spec.reporting)
    for beam_type, rule in rules.items():
        if rule.top_n is not None:
            _check_reports(samples, beam_type, rule.top_n)
    bins = bin_samples(samples, spec, res.dropped)
    for beam_type, rule in rules.items():
        if rule.top_n is not None:
            bins = keep_top_n(bins, beam_type, rule.top_n, res.dropped)
    if spec.rsrp_threshold_dbm is not None:
        res.threshold_dbm = spec.rsrp_threshold_dbm
        below = (bins["rsrp_dbm"] < res.threshold_dbm).to_numpy()
        res.dropped.drop(
            f"bin mean below rsrp_threshold_dbm = {res.threshold_dbm:g}",
            int(bins["samples"][below].sum()),
            int(below.sum()),
        )
        bins = bins[~below].reset_index(drop=True)
    elif len(bins):
        weakest = max(math.floor(bins["rsrp_dbm"].min()), RSRP_MIN_DBM)
        res.threshold_dbm, res.threshold_chosen = float(min(DEFAULT_THRESHOLD_DBM, weakest)), True
    if len(bins) == 0:
        reasons = "; ".join(f"{why}: {n:,}" for why, n in res.dropped.samples.items())
        raise DataError(
            f"import: no bin kept; all {res.samples_read:,} samples were dropped ({reasons or 'no samples read'})."
        )
    grids, grid_of_bin = grids_of(bins, spec)
    bins = bins.assign(grid_id=grid_of_bin)
    if cloud is not None:
        check_cloud_frame(cloud, Path(str(spec.point_cloud)).name, grids, spec.grid_size_m, origin)
        res.point_cloud_points = cloud.num_points
    res.samples_kept, res.bins, res.grids = int(bins["samples"].sum()), len(bins), len(grids)
    res.cells, res.rounds, res.bins_table = len(cells[1]), sorted(cells), bins
    _write(out, spec, meta_dict, res, cells, folders, grids, bins, table_format)
    return res


def _read_cloud(path: str) -> PointCloud:
    """The import's point cloud, read as ``rflscm check`` reads it; coordinates far off say which frame is needed."""
    try:
        return read_point_cloud(path)
    except DataError as exc:
        if "implausible" not in str(exc):
            raise
        raise DataError(
            f"{str(exc).rstrip('.')}. `rflscm import` needs the cloud in its local frame: x east, y north [m] from "
            'the origin, z [m] above the origin\'s height (docs/your-own-data.md, "The building point cloud").'
        ) from None


def _meta_dict(spec: ImportSpec, cells: dict[int, pd.DataFrame], origin: Origin | None) -> dict[str, Any]:
    freqs = cells[1]["freq_hz"].value_counts(sort=False)
    freqs = freqs.sort_index(ascending=False).sort_values(ascending=False, kind="stable")
    return {
        "name": spec.name,
        "description": spec.description or "imported by `rflscm import` from raw samples and a cell list",
        "origin": None if origin is None else to_dict(origin),
        "rsrp_threshold_dbm": -120.0,
        **({"reporting": spec.reporting} if spec.reporting else {}),
        "frequencies_hz": [float(f) for f in freqs.index],
        "codebooks": spec.codebooks,
        "rounds": {r: {"cells": "cells"} for r in cells},
        "grids": "grids",
    }


def _check_beams(samples: pd.DataFrame, cells: dict[int, pd.DataFrame], meta: ScenarioMeta) -> None:
    """A beam index beyond the cell's codebook stops the import naming the sample's file, row and value."""
    for rnd, table in cells.items():
        for beam_type in BEAM_TYPES:
            col = f"{beam_type}_codebook"
            if col not in table.columns:
                raise DataError(f"the cell list has no `{col}`; add the column or `cell_defaults: {{{col}: NAME}}`.")
            unknown = sorted(set(table[col].astype(str)) - set(meta.codebooks))
            if unknown:
                raise DataError(
                    f"the cell list names codebook(s) {unknown} that `codebooks` does not define; "
                    f"defined: {', '.join(meta.codebooks)}."
                )
            size = table.set_index("cell_id")[col].map(lambda n: meta.codebooks[n].num_beams)
            mine = samples[(samples["round"] == rnd).to_numpy() & (samples["beam_type"] == beam_type).to_numpy()]
            bad = mine["beam_id"].to_numpy() >= size.reindex(mine["cell_id"]).to_numpy()
            if bad.any():
                row = mine[bad].iloc[0]
                raise DataError(
                    f"{row['file']} row {row['row']}: `beam_id` = {row['beam_id']} is beyond the {beam_type} codebook "
                    f"of cell {row['cell_id']} ({int(size[row['cell_id']])} beams, 0-based); "
                    f"{int(bad.sum()) - 1} more sample(s) have the same problem."
                )


def _check_reports(samples: pd.DataFrame, beam_type: str, top_n: int) -> None:
    """A raw report (samples of one file, time, cell and beam type) carrying more than ``top_n`` beams is an error."""
    mine = samples[(samples["beam_type"] == beam_type).to_numpy() & (samples["time"] != "").to_numpy()]
    if len(mine) == 0:
        return
    counts = mine.groupby(["file", "time", "cell_id"], sort=False)["beam_id"].transform("size").to_numpy()
    over = counts > top_n
    if over.any():
        row = mine[over].iloc[0]
        raise DataError(
            f"{row['file']} row {row['row']}: `time` = {row['time']!r} holds a {beam_type} report of cell "
            f"{row['cell_id']} with {int(counts[over][0])} beams, more than the declared "
            f"`reporting.{beam_type}.top_n` = {top_n}; declare the rule the network used."
        )


def _write(
    out: Path,
    spec: ImportSpec,
    meta_dict: dict[str, Any],
    res: ImportResult,
    cells: dict[int, pd.DataFrame],
    folders: dict[int, str],
    grids: pd.DataFrame,
    bins: pd.DataFrame,
    table_format: str,
) -> None:
    ext = ".csv" if table_format == "csv" else ".parquet"
    out.mkdir(parents=True, exist_ok=True)
    for rnd, table in cells.items():
        write_table(table[[c for c in CELL_COLUMNS if c in table.columns]], out / f"cells_round{rnd}{ext}")
        copy_elements(table, folders[rnd], out)
    write_table(cells[1][["cell_id", "cell_name", "pci", "carrier_hz"]], out / f"{CELL_MAP_FILE}{ext}")
    write_table(grids, out / f"grids{ext}")
    meas = bins[["round", "cell_id", "grid_id", "beam_type", "beam_id", "rsrp_dbm"]]
    write_table(meas, out / f"measurements{ext}")
    write_table(
        bins[["round", "cell_id", "grid_id", "beam_type", "beam_id", "samples", "std_db"]], out / f"{BINS_FILE}{ext}"
    )
    meta = {**meta_dict, "rsrp_threshold_dbm": float(res.threshold_dbm)}
    meta["rounds"] = {r: {"cells": f"cells_round{r}{ext}"} for r in cells}
    meta["grids"], meta["measurements"] = f"grids{ext}", f"measurements{ext}"
    if spec.terrain is not None:
        name = "terrain" + Path(spec.terrain).suffix.lower()
        shutil.copyfile(spec.terrain, out / name)
        meta["terrain"] = name
    if spec.point_cloud is not None:
        name = "point_cloud" + Path(spec.point_cloud).suffix.lower()
        shutil.copyfile(spec.point_cloud, out / name)
        meta["point_cloud"] = name
    meta["simulation"] = {
        "generator": "rflscm import",
        "import": {
            "grid_size_m": spec.grid_size_m,
            "min_samples": spec.min_samples,
            "outlier_k": spec.outlier_k,
            "max_distance_m": spec.max_distance_m,
            "ambiguity_ratio": spec.ambiguity_ratio,
            "heights": "above the terrain" if spec.terrain is not None else "above flat ground at the origin's height",
            "samples_read": res.samples_read,
            "samples_kept": res.samples_kept,
            "dropped": dict(res.dropped.samples),
            "bins_table": f"{BINS_FILE}{ext}",
            "cell_names": f"{CELL_MAP_FILE}{ext}",
        },
    }
    text = yaml.safe_dump(meta, sort_keys=False, allow_unicode=True, default_flow_style=None)
    (out / "scenario.yaml").write_text(text)
