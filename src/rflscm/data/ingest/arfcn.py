"""Channel numbers → carrier frequencies [Hz], vectorised.

* NR-ARFCN, 3GPP TS 38.104 §5.4.2.1 (Table 5.4.2.1-1): F_REF = F_REF-Offs + ΔF_Global (N_REF − N_REF-Offs)
  with three ranges: 0–3000 MHz in 5 kHz steps (N 0…599 999), 3000–24 250 MHz in 15 kHz steps
  (N 600 000…2 016 666) and 24 250.08–100 000 MHz in 60 kHz steps (N 2 016 667…3 279 165).
* LTE EARFCN (downlink), 3GPP TS 36.101 §5.7.3: F_DL = F_DL_low + 0.1 (N_DL − N_Offs-DL) [MHz] for the
  bands listed in :data:`EARFCN_BANDS` (the common FDD and TDD bands); another number is refused.
"""

from __future__ import annotations

import numpy as np

NR_RANGES = (  # (N_low, N_high, F_offs [Hz], ΔF_global [Hz], N_offs)
    (0, 599_999, 0.0, 5e3, 0),
    (600_000, 2_016_666, 3000e6, 15e3, 600_000),
    (2_016_667, 3_279_165, 24250.08e6, 60e3, 2_016_667),
)

EARFCN_BANDS = {  # band: (F_DL_low [MHz], N_Offs-DL, N_DL high)
    1: (2110.0, 0, 599),
    2: (1930.0, 600, 1199),
    3: (1805.0, 1200, 1949),
    4: (2110.0, 1950, 2399),
    5: (869.0, 2400, 2649),
    7: (2620.0, 2750, 3449),
    8: (925.0, 3450, 3799),
    12: (729.0, 5010, 5179),
    13: (746.0, 5180, 5279),
    20: (791.0, 6150, 6449),
    25: (1930.0, 8040, 8689),
    28: (758.0, 9210, 9659),
    38: (2570.0, 37750, 38249),
    39: (1880.0, 38250, 38649),
    40: (2300.0, 38650, 39649),
    41: (2496.0, 39650, 41589),
    42: (3400.0, 41590, 43589),
    43: (3600.0, 43590, 45589),
    66: (2110.0, 66436, 67335),
    71: (617.0, 68586, 68935),
}
"""LTE downlink bands: first frequency, offset and last EARFCN (TS 36.101 Table 5.7.3-1)."""


def nr_arfcn_to_hz(n: np.ndarray) -> np.ndarray:
    """Carrier [Hz] ``[num]`` of NR-ARFCNs ``[num]``; NaN where a number lies outside 0…3 279 165."""
    n = np.asarray(n, dtype=np.float64)
    out = np.full(n.shape, np.nan)
    for low, high, f_offs, step, n_offs in NR_RANGES:
        inside = (n >= low) & (n <= high) & (n == np.round(n))
        out = np.where(inside, f_offs + step * (n - n_offs), out)
    return out


def hz_to_nr_arfcn(freq_hz: np.ndarray) -> np.ndarray:
    """NR-ARFCN ``[num]`` (int64) of carriers [Hz] on the global raster (rounded to the nearest raster point)."""
    f = np.asarray(freq_hz, dtype=np.float64)
    out = np.zeros(f.shape, dtype=np.int64)
    for low, _high, f_offs, step, n_offs in NR_RANGES:
        inside = f >= (f_offs if low else 0.0)
        out = np.where(inside, np.round((f - f_offs) / step).astype(np.int64) + n_offs, out)
    return out


def earfcn_to_hz(n: np.ndarray) -> np.ndarray:
    """Downlink carrier [Hz] ``[num]`` of LTE EARFCNs ``[num]``; NaN where the number is in no listed band."""
    n = np.asarray(n, dtype=np.float64)
    out = np.full(n.shape, np.nan)
    for f_low, n_offs, n_high in EARFCN_BANDS.values():
        inside = (n >= n_offs) & (n <= n_high) & (n == np.round(n))
        out = np.where(inside, (f_low + 0.1 * (n - n_offs)) * 1e6, out)
    return out
