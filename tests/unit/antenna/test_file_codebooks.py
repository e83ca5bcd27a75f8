"""File codebooks: explicit element weights and measured per-beam gain tables (issue 25, deliverable 2)."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from rflscm.antenna import (
    ArrayGeometry,
    CellAntenna,
    DFTCodebook,
    SSBCodebook,
    TR38901Element,
    beam_weights,
    codebook_from_dict,
    sensing_matrix,
    wavelength_of,
)
from rflscm.errors import ConfigError
from rflscm.geometry import AngleGrid

GRID = AngleGrid()
WL = wavelength_of(3.5e9)
ANT = CellAntenna(azimuth_deg=37.0, mech_tilt_deg=4.0, elec_tilt_deg=6.0)


def _weights_csv(w: np.ndarray, path: Path) -> None:
    b, h, v = np.meshgrid(*(np.arange(n) for n in w.shape), indexing="ij")
    pd.DataFrame(
        {
            "beam_id": b.ravel(),
            "element_h": h.ravel(),
            "element_v": v.ravel(),
            "re": w.real.ravel(),
            "im": w.imag.ravel(),
        }
    ).to_csv(path, index=False)


@pytest.mark.parametrize("suffix", [".npy", ".csv"])
@pytest.mark.parametrize("book", [DFTCodebook(), SSBCodebook()])
def test_codebook_as_explicit_weights_gives_the_same_sensing_matrix(tmp_path: Path, suffix: str, book) -> None:
    w = book.weights(ANT.array, WL).numpy() * 3.7  # any scale: the file is normalised to unit power per beam
    path = tmp_path / f"w{suffix}"
    np.save(path, w) if suffix == ".npy" else _weights_csv(w, path)
    loaded = codebook_from_dict({"type": "weights", "file": path.name}, root=tmp_path)
    assert loaded.num_beams == book.num_beams
    a_ref = sensing_matrix(ANT, book, GRID, WL, dtype=torch.float64)
    a_new = sensing_matrix(ANT, loaded, GRID, WL, dtype=torch.float64)
    torch.testing.assert_close(a_new, a_ref, rtol=1e-6, atol=1e-6 * float(a_ref.max()))


def _pattern_table(book, antenna: CellAntenna, step_deg: float) -> pd.DataFrame:
    """Each beam's gain [dBi] sampled on an az × el grid in the antenna frame (electrical tilt included)."""
    az = np.arange(-180.0, 180.0, step_deg)
    el = np.arange(-90.0, 90.0 + 1e-9, step_deg)
    e, a = np.meshgrid(np.deg2rad(el), np.deg2rad(az), indexing="ij")
    local = np.stack((np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)), -1).reshape(-1, 3)
    bare = CellAntenna(
        elec_tilt_deg=antenna.elec_tilt_deg, element=antenna.element, array=antenna.array, tx_power_dbm=0.0
    )
    world = torch.as_tensor(local @ bare.rotation().T)  # antenna frame → world, as sensing_matrix expects
    g = sensing_matrix(bare, book, world, WL, dtype=torch.float64).numpy()  # P_t = 1 mW → gain
    beams = np.repeat(np.arange(book.num_beams), local.shape[0])
    ee, aa = np.meshgrid(el, az, indexing="ij")
    return pd.DataFrame(
        {
            "beam_id": beams,
            "azimuth_deg": np.tile(aa.ravel(), book.num_beams),
            "elevation_deg": np.tile(ee.ravel(), book.num_beams),
            "gain_dbi": 10 * np.log10(np.maximum(g.ravel(), 1e-30)),
        }
    )


def _rsrp_error_db(book, step_deg: float, tmp_path: Path) -> float:
    """Largest |RSRP(pattern) − RSRP(weights)| [dB] over beams and random APS (strongest beams)."""
    _pattern_table(book, ANT, step_deg).to_parquet(tmp_path / "p.parquet")
    pattern = codebook_from_dict({"type": "pattern", "file": "p.parquet"}, root=tmp_path)
    a_ref = sensing_matrix(ANT, book, GRID, WL, dtype=torch.float64)
    a_pat = sensing_matrix(ANT, pattern, GRID, WL, dtype=torch.float64)
    rng = np.random.default_rng(0)
    x = torch.as_tensor(rng.exponential(size=(GRID.num_bins, 64)) ** 3)  # spread APS over many bins
    r_ref, r_pat = a_ref @ x, a_pat @ x
    return float((10 * torch.log10(r_pat / r_ref)).abs().max())


@pytest.mark.parametrize("book", [DFTCodebook(), SSBCodebook()])
def test_pattern_table_sampled_from_a_codebook_gives_rsrp_within_the_interpolation_error(tmp_path, book) -> None:
    # docs/codebooks.md states the measured error: 1° tables ≤ 0.05 dB, 5° tables ≤ 1 dB (DFT, worst beam)
    fine = _rsrp_error_db(book, 1.0, tmp_path)
    coarse = _rsrp_error_db(book, 5.0, tmp_path)
    assert fine < 0.05
    assert coarse < 1.2
    assert fine < coarse


def test_pattern_codebook_ignores_element_and_tilt_but_follows_rotation(tmp_path: Path) -> None:
    book = DFTCodebook()
    _pattern_table(book, ANT, 2.0).to_csv(tmp_path / "p.csv", index=False)
    pattern = codebook_from_dict({"type": "pattern", "file": "p.csv"}, root=tmp_path)
    a = sensing_matrix(ANT, pattern, GRID, WL)
    rotated = CellAntenna(azimuth_deg=ANT.azimuth_deg + 90.0, mech_tilt_deg=ANT.mech_tilt_deg, elec_tilt_deg=0.0)
    b = sensing_matrix(rotated, pattern, GRID, WL)
    _el, az = GRID.bin_angles()
    peak_a, peak_b = np.rad2deg(az[a.argmax(1).numpy()]), np.rad2deg(az[b.argmax(1).numpy()])
    turn = (peak_b - peak_a + 180.0) % 360.0 - 180.0
    # engineering azimuth turns clockwise, the grid's azimuth counter-clockwise: −90° in the grid
    assert np.median(turn) == pytest.approx(-90.0, abs=6.0)
    with pytest.raises(ConfigError, match="cannot be re-steered"):
        beam_weights(pattern, ANT, WL)


@pytest.mark.parametrize(
    ("content", "spec", "message"),
    [
        (np.zeros((2, 8, 4), complex), {}, "beam 0 has all-zero weights"),
        (np.full((2, 8, 4), np.nan), {}, "finite"),
        (np.ones((2, 8)), {}, "[num_beams, num_h, num_v]"),
        (None, {"file": "../outside.npy"}, "outside the scenario folder"),
        (None, {"file": "missing.npy"}, "file not found"),
    ],
)
def test_weights_file_is_validated(tmp_path: Path, content, spec, message) -> None:
    root = tmp_path / "scenario"
    root.mkdir()
    np.save(tmp_path / "outside.npy", np.ones((1, 8, 4), complex))
    if content is not None:
        np.save(root / "w.npy", content)
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")) as exc:
        codebook_from_dict({"type": "weights", "file": "w.npy", **spec}, where="codebooks.vendor", root=root)
    assert "`codebooks.vendor`" in str(exc.value) and "\n" not in str(exc.value)


def test_weights_must_fit_the_array(tmp_path: Path) -> None:
    np.save(tmp_path / "w.npy", np.ones((3, 4, 4), complex))
    book = codebook_from_dict({"type": "weights", "file": "w.npy"}, root=tmp_path)
    with pytest.raises(ConfigError, match="4 × 4 elements per beam, which does not match the 8 × 4 array"):
        book.weights(ArrayGeometry(num_h=8, num_v=4), WL)


def test_pattern_table_needs_a_full_grid(tmp_path: Path) -> None:
    df = _pattern_table(SSBCodebook(), CellAntenna(element=TR38901Element()), 30.0).iloc[:-1]
    df.to_csv(tmp_path / "p.csv", index=False)
    with pytest.raises(ConfigError, match="every beam_id 0…7 at every azimuth × elevation"):
        codebook_from_dict({"type": "pattern", "file": "p.csv"}, root=tmp_path)
