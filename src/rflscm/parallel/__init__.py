"""Ray as the engine: prediction and evaluation spread over local cores or a Ray cluster in chunks.

``--workers 1`` (the default) runs in-process and never imports ray; ``--workers N`` starts a local Ray on
demand; ``--ray-address ADDR`` joins an existing cluster.  What runs in parallel is the expensive part of a
prediction, a source's APS of the (cell, grid) pairs asked for: the pairs are planned into exactly the
calls the serial path makes (:mod:`rflscm.parallel.plan`), the calls are spread over workers that each load
the checkpoint once (:mod:`rflscm.parallel.aps`), and their answers fill the APS cache the serial code then
reads, in the original order, so the results are those of the serial path (bit-identical with ``--threads 1``).
Tiles train as Ray tasks (:mod:`rflscm.parallel.tiles`), and ``simulate`` traces and computes RSRP per site
through an ordered map over Ray actors (:mod:`rflscm.parallel.work`).

This module imports neither torch nor ray (the CLI reads its options at start-up); the work is in
:mod:`rflscm.parallel.aps`, :mod:`rflscm.parallel.tiles` and :mod:`rflscm.parallel.work`.
"""

from rflscm.parallel.engine import Engine, RayAddressOption, WorkersOption, ray_session

__all__ = ["Engine", "RayAddressOption", "WorkersOption", "ray_session"]
