"""Write the second element pattern that ships with rflscm: an embedded patch element of a 3.5 GHz panel.

    PYTHONPATH=src python scripts/make_patch_element.py   # -> src/rflscm/assets/antennas/patch_90x70deg_3500MHz.msi

A *synthesised* pattern with the traits of measured embedded patch elements in massive-MIMO panels. It is
not a vendor file. Those traits are a wider horizontal beam than TR 38.901's 65° (90° HPBW), a narrower
vertical one (70°), 7 dBi peak gain, a 25 dB front-back ratio instead of 30 dB, and a ±1 dB ripple from
ground-plane edge diffraction beyond ±60°. The field regime's truth can use it (`field_model.real_element`)
while the models keep the declared `tr38901`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rflscm.antenna.element import MeasuredElement
from rflscm.antenna.msi import write_msi

OUT = Path(__file__).resolve().parents[1] / "src" / "rflscm" / "assets" / "antennas" / "patch_90x70deg_3500MHz.msi"


def cut(hpbw_deg: float, fbr_db: float, ripple_db: float) -> tuple[float, ...]:
    """Loss [dB] at 0…359° of one cut: 12 (a / HPBW)², capped at the front-back ratio, with an edge ripple."""
    angle = np.arange(360.0)
    off = np.minimum(angle, 360.0 - angle)  # angle off boresight [deg]
    loss = np.minimum(12.0 * (off / hpbw_deg) ** 2, fbr_db)
    ripple = ripple_db * np.sin(np.deg2rad(4.0 * off)) * (off > 60.0)
    return tuple(np.round(np.clip(loss + ripple, 0.0, fbr_db), 2))


def main() -> None:
    element = MeasuredElement(
        max_gain_dbi=7.0,
        horizontal_loss_db=cut(90.0, 25.0, 1.0),
        vertical_loss_db=cut(70.0, 25.0, 1.0),
        max_attenuation_db=25.0,
        name="rflscm-synthetic-patch-90x70deg-3500MHz",
    )
    write_msi(element, OUT, frequency_mhz=3500.0)
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
