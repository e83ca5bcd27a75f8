import numpy as np
import pytest
import torch

from rflscm.antenna import MeasuredElement, read_msi, sample_msi_path, write_msi
from rflscm.errors import DataError


def test_shipped_sample_msi_loads_and_peaks_at_boresight():
    e = read_msi(sample_msi_path())
    assert len(e.horizontal_loss_db) == 360 and len(e.vertical_loss_db) == 360
    dirs = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]], dtype=torch.float64)
    g = e.gain_db(dirs)
    assert g[0].item() == pytest.approx(e.max_gain_dbi)
    assert g[0] > g[1] > g[2]


def test_msi_round_trip(tmp_path):
    e = MeasuredElement(
        max_gain_dbi=17.15,
        horizontal_loss_db=tuple(np.linspace(0, 20, 8)),
        vertical_loss_db=(0.0, 3.0, 30.0, 3.0),
        name="x",
    )
    write_msi(e, tmp_path / "a.msi", frequency_mhz=3500)
    back = read_msi(tmp_path / "a.msi")
    assert back.max_gain_dbi == pytest.approx(e.max_gain_dbi)
    np.testing.assert_allclose(back.horizontal_loss_db, e.horizontal_loss_db, atol=1e-2)
    np.testing.assert_allclose(back.vertical_loss_db, e.vertical_loss_db, atol=1e-2)


def test_msi_dbd_gain_is_converted(tmp_path):
    p = tmp_path / "d.msi"
    p.write_text("NAME d\nGAIN 15 dBd\nHORIZONTAL 2\n0 0\n180 20\nVERTICAL 2\n0 0\n180 20\n")
    assert read_msi(p).max_gain_dbi == pytest.approx(17.15)


@pytest.mark.parametrize(
    "body, message",
    [
        ("GAIN 15 dBi\nHORIZONTAL 2\n0 0\n180 x\nVERTICAL 2\n0 0\n180 1\n", "line 4"),
        ("GAIN 15 dBi\nHORIZONTAL 2\n0 0\n170 1\nVERTICAL 2\n0 0\n180 1\n", "line 4"),
        ("GAIN 15 dBi\nHORIZONTAL 3\n0 0\n120 1\n", "line 2"),
        ("GAIN 15 dBi\nHORIZONTAL 2\n0 0\n180 1\n", "VERTICAL"),
        ("HORIZONTAL 2\n0 0\n180 1\nVERTICAL 2\n0 0\n180 1\n", "GAIN"),
        ("GAIN high\n", "line 1"),
        ("GAIN 15\nHORIZONTAL 2\n0 0\n180 -4\nVERTICAL 2\n0 0\n180 1\n", "line 4"),
    ],
)
def test_malformed_msi_names_the_line(tmp_path, body, message):
    p = tmp_path / "bad.msi"
    p.write_text(body)
    with pytest.raises(DataError, match=message):
        read_msi(p)


def test_missing_msi_file(tmp_path):
    with pytest.raises(DataError, match="not found"):
        read_msi(tmp_path / "nope.msi")
