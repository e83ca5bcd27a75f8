"""Time RF-LSCM's pass after training (level correction, pair anchors, pair posterior) on one trained state.

    PYTHONPATH=src python scripts/finish_timing.py snapshot SCENARIO STEPS STATE.pt
    PYTHONPATH=src python scripts/finish_timing.py time STATE.pt [REPEATS]

``snapshot`` trains the quick preset (3-minute budget schedule, one thread) for STEPS steps and pickles the
whole model, training data included; ``time`` loads it and runs ``finish_training`` REPEATS times (default 3),
printing each wall time and the λ chosen with its held-aside scores.  The pickle holds the model object, so
the code that times it is whatever ``PYTHONPATH`` points at: run ``time`` once with this tree's ``src`` and
once with an older commit's (``git archive <commit> src | tar -x -C DIR``), side by side on the two cores,
to compare the two passes on the same weights.  The process is set up as ``rflscm`` sets itself up
(``rflscm.runtime.keep_freed_memory`` where the code has it).  Used for DECISIONS.md, "Learning faster".
"""

import contextlib
import sys
import time

import torch

torch.set_num_threads(1)
with contextlib.suppress(ImportError):  # older commits have no rflscm.runtime
    from rflscm.runtime import keep_freed_memory

    print("allocator settings applied:", keep_freed_memory())


def snapshot(scen_dir: str, steps: int, out: str) -> None:
    from rflscm.data import load_scenario
    from rflscm.eval.protocols import AdjustProtocol, fit_with_protocol
    from rflscm.geometry import AngleGrid
    from rflscm.models import MODEL_REGISTRY

    scenario = load_scenario(scen_dir)
    model = MODEL_REGISTRY["rflscm"].build("quick", AngleGrid(), "cpu")

    class Stop(Exception):
        pass

    def stop_at(metrics):
        if metrics["step"] >= steps:
            raise Stop

    with contextlib.suppress(Stop):
        fit_with_protocol(model, scenario, AdjustProtocol(), progress=False, callback=stop_at, budget_s=180.0)
    torch.save(model, out)
    print("saved step", model.step)


def time_finish(path: str, repeats: int) -> None:
    model = torch.load(path, weights_only=False)
    for _ in range(repeats):
        model._levels_step = model._pairs_step = None  # measure everything again
        start = time.perf_counter()
        model.finish_training()
        post = model.corrections.posterior
        scores = {k: round(v, 4) for k, v in post.scores.items()} if post is not None else None
        print(f"finish {time.perf_counter() - start:.2f} s, λ {post.lam if post else None}, held-aside {scores}")


if __name__ == "__main__":
    if sys.argv[1] == "snapshot":
        snapshot(sys.argv[2], int(sys.argv[3]), sys.argv[4])
    else:
        time_finish(sys.argv[2], int(sys.argv[3]) if len(sys.argv) > 3 else 3)
