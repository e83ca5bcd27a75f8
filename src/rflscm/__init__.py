"""rflscm — radiance-field localized statistical channel models from multi-beam RSRP."""

import time as _time

__version__ = "0.1.0"

LOADED_AT = _time.perf_counter()
"""``time.perf_counter()`` when the package began loading: a console command's ``--minutes`` budget counts from here,
so that the imports (torch's among them) are inside it."""
