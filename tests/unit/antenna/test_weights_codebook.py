"""Vendors' beam sets as explicit element weights (``type: weights``), and any kind serving either beam type."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from rflscm.antenna import ArrayGeometry, CellAntenna, DFTCodebook, SSBCodebook, WeightsCodebook, sensing_matrix
from rflscm.data import load_scenario, save_scenario
from rflscm.data.codebook_files import read_weights_codebook, weights_table
from rflscm.data.examples import tiny_scenario
from rflscm.errors import DataError
from rflscm.geometry.grid import AngleGrid

WAVELENGTH = 299_792_458.0 / 3.5e9
ARRAY = ArrayGeometry(num_h=8, num_v=4)


def _antenna() -> CellAntenna:
    return CellAntenna(azimuth_deg=30.0, mech_tilt_deg=4.0, elec_tilt_deg=3.0, array=ARRAY)


def _as_file(root: Path, book: DFTCodebook | SSBCodebook, name: str) -> WeightsCodebook:
    values = book.weights(ARRAY, WAVELENGTH).numpy() * 3.7  # any scale: each beam is normalised when read
    table = weights_table(WeightsCodebook.of(values, name, ""))
    table.to_csv(root / name, index=False) if name.endswith(".csv") else np.save(root / name, values)
    return read_weights_codebook(root, WeightsCodebook(file=name), "test")


@pytest.mark.parametrize("name", ["dft.csv", "dft.npy"])
def test_a_dft_codebook_given_as_weights_gives_the_same_sensing_matrix(tmp_path: Path, name: str) -> None:
    dft = DFTCodebook()
    book = _as_file(tmp_path, dft, name)
    grid = AngleGrid(num_el=31, num_az=24, el_step_deg=6.0)
    a_ref = sensing_matrix(_antenna(), dft, grid, WAVELENGTH, dtype=torch.float64)
    a_file = sensing_matrix(_antenna(), book, grid, WAVELENGTH, dtype=torch.float64)
    assert book.num_beams == dft.num_beams == 32
    rel = (a_file - a_ref).abs().max() / a_ref.abs().max()
    assert float(rel) < 1e-6
    assert book.sha256 == hashlib.sha256((tmp_path / name).read_bytes()).hexdigest()


def test_weights_are_normalised_per_beam(tmp_path: Path) -> None:
    book = _as_file(tmp_path, SSBCodebook(), "ssb.csv")
    power = (np.abs(book.values) ** 2).sum(axis=(1, 2))
    np.testing.assert_allclose(power, 1.0, atol=1e-12)


def test_weights_that_do_not_fit_the_array_are_refused(tmp_path: Path) -> None:
    book = _as_file(tmp_path, DFTCodebook(), "dft.csv")
    with pytest.raises(Exception, match="for a 8 × 4 array, not the 4 × 4 array"):
        book.weights(ArrayGeometry(num_h=4, num_v=4), WAVELENGTH)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda df: df.iloc[1:], "rows for 8 beams"),
        (lambda df: df.assign(re=np.where(df.beam_id == 2, 0.0, df.re), im=np.where(df.beam_id == 2, 0.0, df.im)),
         "beam 2 has all-zero weights"),
        (lambda df: df.assign(element_h=np.where(df.index == 3, -1, df.element_h)), "must be ≥ 0"),
        (lambda df: df.assign(re=df.re.astype(object).where(df.index != 5, "N/A")), "`re`"),
    ],
)  # fmt: skip
def test_bad_weight_tables_are_one_line_errors(tmp_path: Path, edit, message: str) -> None:
    _as_file(tmp_path, SSBCodebook(), "w.csv")
    import pandas as pd

    edit(pd.read_csv(tmp_path / "w.csv")).to_csv(tmp_path / "w.csv", index=False)
    with pytest.raises(DataError, match=message) as info:
        read_weights_codebook(tmp_path, WeightsCodebook(file="w.csv"), "scenario.yaml: `codebooks.v.file`")
    assert "\n" not in str(info.value)


def test_a_weights_file_outside_the_scenario_or_changed_since_is_refused(tmp_path: Path) -> None:
    (tmp_path / "scen").mkdir()
    _as_file(tmp_path, SSBCodebook(), "w.csv")
    with pytest.raises(DataError, match="outside the scenario folder"):
        read_weights_codebook(tmp_path / "scen", WeightsCodebook(file="../w.csv"), "x")
    with pytest.raises(DataError, match="differs from the `sha256`"):
        read_weights_codebook(tmp_path, WeightsCodebook(file="w.csv", sha256="0" * 64), "x")


def test_any_codebook_serves_either_beam_type_end_to_end(tmp_path: Path) -> None:
    """A DFT set as SSB beams and a vendor weights file as CSI-RS beams load, predict and train WNOMP."""
    from rflscm.eval import fit_with_protocol
    from rflscm.models import MODEL_REGISTRY
    from rflscm.models.source import predict_rsrp

    root = tiny_scenario(tmp_path / "tiny", seed=3)
    meta = yaml.safe_load((root / "scenario.yaml").read_text())
    scen = load_scenario(root)
    wavelength = 299_792_458.0 / float(scen.cells[1]["freq_hz"].iloc[0])
    array = ArrayGeometry(num_h=int(scen.cells[1]["array_nh"].iloc[0]), num_v=int(scen.cells[1]["array_nv"].iloc[0]))
    values = scen.meta.codebooks["csi8"].weights(array, wavelength).numpy()
    weights_table(WeightsCodebook.of(values, "vendor.csv", "")).to_csv(root / "vendor.csv", index=False)
    meta["codebooks"]["vendor"] = {"type": "weights", "file": "vendor.csv"}
    (root / "scenario.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    for cells in root.glob("cells_round*.csv"):
        text = cells.read_text().replace(",ssb8,csi8", ",csi8,vendor")
        cells.write_text(text)
    swapped = load_scenario(root)
    assert set(swapped.cells[1]["ssb_codebook"]) == {"csi8"} and set(swapped.cells[1]["csi_codebook"]) == {"vendor"}
    copy = load_scenario(save_scenario(swapped, tmp_path / "copy"))  # the weights file travels with the scenario
    assert copy.meta.codebooks["vendor"] == swapped.meta.codebooks["vendor"]
    np.testing.assert_array_equal(copy.meta.codebooks["vendor"].values, swapped.meta.codebooks["vendor"].values)
    assert copy.fingerprint() == swapped.fingerprint()
    cell = int(swapped.cells[1]["cell_id"].iloc[0])
    assert swapped.codebook(cell, "csi", 1).num_beams == 8
    model = MODEL_REGISTRY["wnomp"].build({}, AngleGrid(num_el=31, num_az=24, el_step_deg=6.0), "cpu")
    fit_with_protocol(model, swapped, None, progress=False)
    m = swapped.measurements
    m = m[(m["round"] == 1) & (m["beam_type"] == "csi")].dropna(subset=["rsrp_dbm"])
    pairs = m[["cell_id", "grid_id"]].drop_duplicates().reset_index(drop=True)
    pred = predict_rsrp(model, swapped, 1, "csi", pairs)  # [pairs, 8] through the vendor weights
    lookup = pairs.reset_index().merge(m, on=["cell_id", "grid_id"])
    fitted = pred[lookup["index"].to_numpy(), lookup["beam_id"].to_numpy()]
    assert np.isfinite(fitted).all()
    assert np.abs(fitted - lookup["rsrp_dbm"].to_numpy()).mean() < 3.0  # WNOMP fits its own training reports
