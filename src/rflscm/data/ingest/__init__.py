"""Raw drive-test / MR samples and a planning tool's cell list → a scenario (``rflscm import``).

:mod:`~rflscm.data.ingest.spec` (settings and column names), :mod:`~rflscm.data.ingest.cellist` (the cell list),
:mod:`~rflscm.data.ingest.samples` (the samples), :mod:`~rflscm.data.ingest.resolve` ((PCI, carrier) → cell),
:mod:`~rflscm.data.ingest.binning` (grids, outliers, linear means) and :mod:`~rflscm.data.ingest.pipeline`
(all of it, writing the scenario).  See docs/your-own-data.md.
"""

from rflscm.data.ingest.arfcn import earfcn_to_hz, hz_to_nr_arfcn, nr_arfcn_to_hz
from rflscm.data.ingest.pipeline import ImportResult, import_raw
from rflscm.data.ingest.spec import ImportSpec, load_spec

__all__ = ["ImportResult", "ImportSpec", "earfcn_to_hz", "hz_to_nr_arfcn", "import_raw", "load_spec", "nr_arfcn_to_hz"]
