"""RF-LSCM, the radiance-field localized statistical channel model, cut along its seams.

* :mod:`.model` — the ``nn.Module``: construction, ``aps``, the training losses (start here);
* :mod:`.fields` — the VM-tensor fields, FDAM media and the radiance decoder (one rendering stage);
* :mod:`.renderer` — rays, visibility and HiTAM's selection over the stages (no parameters);
* :mod:`.hitam` — HiTAM's coarse-to-fine schedule and block selection;
* :mod:`.scene` — scene box, frame, point-cloud prior and surfaces from a scenario;
* :mod:`.losses` — the LSCM loss;
* :mod:`.corrections` — the post-training pair corrections (levels, anchors, posterior);
* :mod:`.posterior` — the per-pair posterior gains the corrections fit;
* :mod:`.checkpoint` — save, load and resume checks (and the compatibility policy);
* :mod:`.config` — the typed config and its presets.

Decisions where the paper is silent (the constants and options of :mod:`.config`):

* media: 3 passive degrees of freedom (loss on a log scale at a reference carrier, excess real
  index, real μ ≥ 1), each on its own VM factors; FDAM itself is exact, δ^Φ uses the continuous
  branch of log δ; the cumulative |Π δ̃| is capped at 1 (a passivity guard: single FDAM factors
  can exceed 1);
* empty-space skipping from Φ is exact (Φ = 0 samples are inert); a ray's fields are computed
  once per cell and shared by every grid that looks along it; directions a cell's round-1 beams
  cannot see (−30 dB) are not rendered for that cell;
* decoder: the paper's inputs plus the sample-to-grid geometry (direction, half-vector, log
  distances, distance relative to the ray's cone), polar output (log |R|, arg R) with free-space
  and bistatic spreading factors, level calibrated to the data at initialisation;
* attenuation initialised from the classified scan (walls opaque, ground and air transparent);
* HiTAM: coarse rays through block centres with block-mean columns; the refinement model starts
  as a copy of the coarse one, rescaled to the coarse model's level;
* loss in bels by default (paper: linear), L1 relative to each pair's power scale;
* after training, predictions carry (:mod:`.corrections`) a level correction per cell and beam type, a level anchor per
  training pair (the median error left on the pair's own round-1 reports) and a posterior per training
  pair (per-bin gains fitted to those reports under a ridge prior centred on the field,
  :mod:`.posterior`); the paper predicts from the field alone (docs/DECISIONS.md,
  "Learning faster").
"""

from rflscm.models.rflscm.config import RFLSCMConfig, load_rflscm_config, preset_path
from rflscm.models.rflscm.model import RFLSCM

__all__ = ["RFLSCM", "RFLSCMConfig", "load_rflscm_config", "preset_path"]
