"""Any codebook kind serves either beam type, end to end (issue 25, deliverable 2)."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from rflscm.antenna import DFTCodebook, PatternCodebook, SSBCodebook, WeightsCodebook, wavelength_of
from rflscm.data import load_scenario, save_scenario
from rflscm.errors import ConfigError, DataError
from rflscm.geometry import AngleGrid
from rflscm.models import MODEL_REGISTRY
from rflscm.train import fit

sys.path.insert(0, str(Path(__file__).parents[1] / "antenna"))
from test_file_codebooks import _pattern_table

SMALL = AngleGrid(num_el=13, num_az=24, el_min_deg=-90.0, el_step_deg=15.0)


@pytest.mark.parametrize(
    ("csi_kind", "model_name"), [("weights", "wnomp"), ("pattern", "wnomp"), ("pattern", "rflscm")]
)
def test_any_codebook_serves_either_beam_type_and_models_train(
    tiny_dir: Path, edit_table: Callable, edit_yaml: Callable, csi_kind: str, model_name: str
) -> None:
    from rflscm.antenna import CellAntenna

    ssb = SSBCodebook()
    if csi_kind == "weights":  # the SSB beams given as explicit weights serve CSI-RS
        np.save(tiny_dir / "vendor.npy", ssb.weights(CellAntenna().array, wavelength_of(3.5e9)).numpy())
        spec = {"type": "weights", "file": "vendor.npy"}
    else:  # measured per-beam patterns serve CSI-RS
        _pattern_table(ssb, CellAntenna(), 10.0).to_csv(tiny_dir / "vendor.csv", index=False)
        spec = {"type": "pattern", "file": "vendor.csv"}
    edit_yaml(tiny_dir, lambda d: d["codebooks"].update(vendor=spec))
    for name in ("cells_round1.csv", "cells_round2.csv"):  # the DFT book serves SSB, the vendor book CSI-RS
        edit_table(tiny_dir / name, lambda df: df.assign(ssb_codebook="csi8", csi_codebook="vendor"))
    scenario = load_scenario(tiny_dir)
    assert isinstance(scenario.codebook(11, "ssb", 1), DFTCodebook)
    assert isinstance(scenario.codebook(11, "csi", 1), WeightsCodebook if csi_kind == "weights" else PatternCodebook)
    copy = load_scenario(save_scenario(scenario, tiny_dir.parent / "copy"))  # the codebook file travels along
    assert copy.num_beams(11, "csi", 1) == 8
    if model_name == "wnomp":
        model = MODEL_REGISTRY["wnomp"].build(None, SMALL, "cpu")
        assert fit(model, scenario, progress=False)["num_pairs"] == 6
    else:
        sys.path.insert(0, str(Path(__file__).parents[1] / "models"))
        from tiny_rflscm import tiny_config

        model = MODEL_REGISTRY["rflscm"].build(tiny_config(), SMALL, "cpu")
        fit(model, scenario, progress=False)
    for beam_type in ("ssb", "csi"):
        pairs, measured = scenario.rsrp_table(1, beam_type)
        predicted = model.predict_rsrp(scenario, 1, beam_type, pairs)
        assert predicted.shape == measured.shape and np.isfinite(predicted[:, :8]).all()


def test_weights_codebook_that_does_not_fit_the_cell_array_names_the_row(
    tiny_dir: Path, edit_table: Callable, edit_yaml: Callable
) -> None:
    np.save(tiny_dir / "vendor.npy", np.ones((8, 4, 4), complex))
    edit_yaml(tiny_dir, lambda d: d["codebooks"].update(vendor={"type": "weights", "file": "vendor.npy"}))
    edit_table(tiny_dir / "cells_round1.csv", lambda df: df.assign(csi_codebook="vendor"))
    with pytest.raises(DataError, match=r"cells_round1.csv row 1 .*`csi_codebook` = 'vendor' does not fit"):
        load_scenario(tiny_dir)


def test_weights_file_outside_the_scenario_folder_is_refused(tiny_dir: Path, edit_yaml: Callable) -> None:
    np.save(tiny_dir.parent / "elsewhere.npy", np.ones((8, 8, 4), complex))
    edit_yaml(tiny_dir, lambda d: d["codebooks"].update(vendor={"type": "weights", "file": "../elsewhere.npy"}))
    with pytest.raises(ConfigError, match=r"`codebooks.vendor`.*outside the scenario folder"):
        load_scenario(tiny_dir)


def test_msi_element_off_its_band_is_refused_in_one_line(tiny_dir: Path, edit_table: Callable) -> None:
    from rflscm.antenna import read_msi, sample_msi_path

    (tiny_dir / "ant").mkdir()
    (tiny_dir / "ant" / "p.msi").write_bytes(sample_msi_path().read_bytes())  # FREQUENCY 3500 (MHz)
    assert read_msi(tiny_dir / "ant" / "p.msi").frequency_hz == 3.5e9
    # cell 11 is on 3.5 GHz: accepted; cell 12 is on 2.1 GHz: refused
    edit_table(tiny_dir / "cells_round1.csv", lambda df: df.assign(element=["ant/p.msi", ""]))
    edit_table(tiny_dir / "cells_round2.csv", lambda df: df.assign(element=["ant/p.msi", ""]))
    assert load_scenario(tiny_dir).antenna(11).element.frequency_hz == 3.5e9
    edit_table(tiny_dir / "cells_round1.csv", lambda df: df.assign(element=["ant/p.msi", "ant/p.msi"]))
    with pytest.raises(DataError) as exc:
        load_scenario(tiny_dir)
    text = str(exc.value)
    assert "\n" not in text
    assert "cells_round1.csv row 2" in text and "cell 12 on 2100 MHz" in text
    assert "'ant/p.msi' measured at 3500 MHz" in text


def test_pattern_codebook_off_its_band_is_refused(tiny_dir: Path, edit_table: Callable, edit_yaml: Callable) -> None:
    from rflscm.antenna import CellAntenna

    _pattern_table(SSBCodebook(), CellAntenna(), 30.0).to_csv(tiny_dir / "vendor.csv", index=False)
    spec = {"type": "pattern", "file": "vendor.csv", "frequency_hz": 3.5e9}
    edit_yaml(tiny_dir, lambda d: d["codebooks"].update(vendor=spec))
    edit_table(tiny_dir / "cells_round1.csv", lambda df: df.assign(csi_codebook="vendor"))
    with pytest.raises(DataError, match=r"cell 12 on 2100 MHz uses `csi_codebook` = 'vendor' \(file 'vendor.csv'\) "):
        load_scenario(tiny_dir)


def test_optimize_candidates_with_a_pattern_codebook_match_the_sensing_matrix(
    tiny_dir: Path, edit_yaml: Callable
) -> None:
    import dataclasses

    import torch

    from rflscm.antenna import CellAntenna, sensing_matrix
    from rflscm.network.candidates import CellSensing
    from rflscm.network.space import CellOptions

    _pattern_table(SSBCodebook(), CellAntenna(), 10.0).to_csv(tiny_dir / "vendor.csv", index=False)
    edit_yaml(tiny_dir, lambda d: d["codebooks"].update(vendor={"type": "pattern", "file": "vendor.csv"}))
    scenario = load_scenario(tiny_dir)
    values = {
        "ssb_codebook": ("ssb8", "vendor"),
        "elec_tilt_deg": (6.0, 10.0),
        "mech_tilt_deg": (4.0, 9.0),
        "azimuth_deg": (60.0, 90.0),
    }
    dirs = SMALL.directions(dtype=torch.float32)
    sensing = CellSensing(scenario, 11, 1, dirs, CellOptions(11, values, (0, 0, 0, 0)))
    got = sensing.matrices([(1, 0, 1, 1), (1, 1, 1, 1), (0, 1, 1, 1)])
    antenna = dataclasses.replace(scenario.antenna(11, 1), mech_tilt_deg=9.0, azimuth_deg=90.0)
    want = sensing_matrix(antenna, scenario.meta.codebooks["vendor"], dirs, scenario.wavelength_m(11))
    torch.testing.assert_close(got[0], want)
    torch.testing.assert_close(got[1], want)  # the electrical tilt is in the measured pattern: no effect
    tilted = dataclasses.replace(antenna, elec_tilt_deg=10.0)
    ssb = sensing_matrix(tilted, SSBCodebook(), dirs, scenario.wavelength_m(11))
    torch.testing.assert_close(got[2], ssb, rtol=1e-4, atol=1e-4 * float(ssb.max()))
