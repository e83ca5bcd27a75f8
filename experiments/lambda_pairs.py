"""How much the number of pairs λ is chosen on matters: a trained RF-LSCM checkpoint's pass rerun without a time limit
with λ (and the dB mix) chosen on each of COUNTS pairs, each scored on round 2 (issue 28).

    PYTHONPATH=src python experiments/lambda_pairs.py SCENARIO CHECKPOINT 75,150,512

A budget's pass chooses λ on as many pairs as its time allows (``_first_pairs``: 64–100 in a 4-minute demo on the
shipped scenario, 512 without a budget). Each count here is a whole pass without a clock (every pair corrected, the
levels on 16 pairs per cell), so the rows differ only in λ's pairs. Prints per count the groups' λ and the round-2
MAE over the pairs with round-1 reports (SSB all / changed, CSI-RS all / changed) (DECISIONS, "λ is chosen on all
its pairs where the whole pass fits").
"""

import sys

from pass_model import model_before_its_pass  # experiments/pass_model.py

from rflscm.data import load_scenario
from rflscm.eval import run_evaluation
from rflscm.models.rflscm import corrections

scenario_path, checkpoint = sys.argv[1], sys.argv[2]
scenario = load_scenario(scenario_path)
for count in map(int, sys.argv[3].split(",")):
    model = model_before_its_pass(scenario, checkpoint)
    corrections.LAMBDA_PAIRS = count
    model.finish_training()
    seen = run_evaluation(model, scenario, None, oracle=None).metrics["seen"]["mae_db"]
    groups = [(int(g["pairs"]), g["lam"]) for g in model.corrections.posterior.groups]
    rows = " / ".join(f"{seen[bt][subset]:.3f}" for bt in ("ssb", "csi") for subset in ("all", "changed"))
    print(f"λ on {count} pairs: groups (pairs, λ) {groups}; round 2 {rows}", flush=True)
