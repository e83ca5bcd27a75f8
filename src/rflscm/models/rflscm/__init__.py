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
"""

from rflscm.models.rflscm.config import RFLSCMConfig, load_rflscm_config, preset_path
from rflscm.models.rflscm.model import RFLSCM

__all__ = ["RFLSCM", "RFLSCMConfig", "load_rflscm_config", "preset_path"]
