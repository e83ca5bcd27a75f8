"""The scenario that ships with the package (scripts/make_default_scenario.sh)."""

from __future__ import annotations

import numpy as np
import pytest

from rflscm.data import load_scenario
from rflscm.sim import default_scenario_path

MAX_BYTES = 20 * 1024 * 1024


@pytest.fixture(scope="module")
def default():
    return load_scenario(default_scenario_path())


def test_default_scenario_is_shipped_and_small() -> None:
    root = default_scenario_path()
    assert (root / "scenario.yaml").is_file()
    size = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
    assert size <= MAX_BYTES, f"{size / 1e6:.1f} MB"


def test_default_scenario_is_sized_like_the_paper(default) -> None:
    cells = default.cells[1]
    assert default.meta.frequencies_hz[0] == 3.5e9
    assert (cells["freq_hz"] == 3.5e9).sum() == 21 and (cells["freq_hz"] == 2.1e9).sum() == 21
    assert len(default.grids) == 800 and default.rounds() == [1, 2]
    assert default.codebook(cells["cell_id"].iloc[0], "ssb").num_beams == 8
    assert default.codebook(cells["cell_id"].iloc[0], "csi").num_beams == 32
    sim = default.meta.simulation
    assert sim["backend"] in ("sionna", "procedural") and sim["seed"] == 2024
    assert sim["scene"] == ("munich" if sim["backend"] == "sionna" else "city")
    assert len(sim["round2_changes"]) == 14  # a third of each carrier's 21 cells
    for name in ("paths.parquet", "aps.parquet", "rsrp_noiseless.parquet"):
        assert (default.root / "truth" / name).is_file()
    m = default.measurements
    round1 = m[m["round"] == 1]
    assert round1["cell_id"].nunique() >= 30  # most cells are heard somewhere


def test_default_scenario_is_in_the_field_regime(default) -> None:
    from rflscm.data.reporting import check_reporting, reported_fraction

    sim = default.meta.simulation
    assert sim["measurements"] == "field" and sim["field"]["samples_per_grid"] >= 1
    assert default.meta.reporting["ssb"].rule == "sinr" and default.meta.reporting["csi"].rule == "top_n"
    assert check_reporting(default) == []
    frac = reported_fraction(default).set_index(["round", "beam_type"])["fraction"]
    assert 0.2 < frac[(1, "ssb")] < 0.95 and 0.0 < frac[(1, "csi")] < 0.2  # serving-cell top-4 of 32 beams
    for name in ("samples.parquet", "aps_samples.parquet"):
        assert (default.root / "truth" / name).is_file()


def test_oracle_truth_covers_the_default_scenario(default) -> None:
    from rflscm.sim.truth import load_true_aps

    truth = load_true_aps(default)
    pairs, rsrp = default.rsrp_table(1, "ssb")
    # A pair is kept when any beam of either type is reported; take pairs with a reported SSB beam.
    heard = np.flatnonzero(np.isfinite(rsrp).any(axis=1))[:200]
    x = truth.aps(pairs["cell_id"].to_numpy()[heard], pairs["grid_id"].to_numpy()[heard])
    assert x.shape == (len(heard), 6552) and len(heard) == 200
    assert float(x.sum(dim=1).min()) > 0  # a reported pair has paths
