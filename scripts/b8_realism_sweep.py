"""B8: antenna-adjustment MAE as measurement realism grows, one effect at a time and then all together (issue 12).

    PYTHONPATH=src python scripts/b8_realism_sweep.py --out out/b8 [--trace SCENARIO] [--rflscm STEP,STEP]

Every step re-measures the same trace (the shipped munich scenario by default; ``rflscm simulate --from-trace``
semantics, no tracing), then scores on round 2: WNOMP (settings chosen per step on held-aside round-1 beams),
the model floor (oracle), the noise floor, the trivial baseline and, for the steps named in ``--rflscm``,
RF-LSCM (quick preset) and NeRF²-LSCM (``--nerf2``). Writes ``b8.json``, ``b8.md`` (table) and ``b8.png``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import time
from pathlib import Path

from rflscm.data import load_scenario
from rflscm.eval import run_evaluation
from rflscm.eval.protocols import AdjustProtocol, fit_with_protocol
from rflscm.geometry import AngleGrid
from rflscm.models import MODEL_REGISTRY
from rflscm.models.wnomp import WNOMPModel
from rflscm.models.wnomp_select import select_wnomp
from rflscm.sim import default_scenario_path
from rflscm.sim.field import FieldConfig
from rflscm.sim.remeasure import remeasure, trace_config

IDEAL = FieldConfig.ideal()
FULL = FieldConfig()
STEPS: dict[str, tuple[str, FieldConfig]] = {
    "ideal": ("ideal", IDEAL),
    "reporting": ("field", dataclasses.replace(IDEAL, ssb_detection="sinr", csi_serving_only=True, csi_top_n=4)),
    "noise": ("field", dataclasses.replace(IDEAL, fading=True, samples_per_grid=FULL.samples_per_grid,
                                           accuracy_sigma_db=FULL.accuracy_sigma_db)),
    "array_error": ("field", dataclasses.replace(IDEAL, array_amp_sigma_db=FULL.array_amp_sigma_db,
                                                 array_phase_sigma_deg=FULL.array_phase_sigma_deg)),
    "ue_sampling": ("field", dataclasses.replace(IDEAL, positions="random")),
    "all": ("field", FULL),
}  # fmt: skip
"""Step → (regime, effects): the ideal regime, each effect of the field default alone, then all of them."""
ROWS = (("ssb", "all"), ("ssb", "changed"), ("csi", "all"), ("csi", "changed"))


def run_step(name: str, trace: Path, out: Path, neural: list[str], seed: int) -> dict:
    regime, effects = STEPS[name]
    folder = out / name
    if not (folder / "scenario.yaml").is_file():
        shutil.rmtree(folder, ignore_errors=True)
        cfg = dataclasses.replace(trace_config(trace), measurements=regime, field_model=effects, name=f"b8-{name}")
        remeasure(trace, cfg, folder)
    scenario = load_scenario(folder)
    grid = AngleGrid()
    t0 = time.perf_counter()
    chosen, table = select_wnomp(scenario, grid, seed=seed)
    result: dict = {"wnomp_settings": dataclasses.asdict(chosen), "wnomp_selection_s": time.perf_counter() - t0,
                    "wnomp_selection": table.to_dict(orient="records")}  # fmt: skip
    models = [("wnomp", WNOMPModel(chosen, grid, "cpu"))]
    models += [(m, MODEL_REGISTRY[m].build("quick", grid, "cpu")) for m in neural]
    for label, model in models:
        t0 = time.perf_counter()
        fit_with_protocol(model, scenario, AdjustProtocol(), progress=False)
        metrics = run_evaluation(model, scenario, AdjustProtocol(), oracle="auto").metrics
        result[label] = {"mae_db": metrics["mae_db"], "bias_db": metrics["bias_db"], "fit_s": time.perf_counter() - t0}
        for key, floor in (("model_floor", "oracle_mae_db"), ("noise_floor", "noise_floor_mae_db"),
                           ("trivial", "trivial_mae_db")):  # fmt: skip
            result[key] = {"mae_db": metrics[floor]}
    counts = scenario.measurements.groupby(["round", "beam_type"])["rsrp_dbm"].apply(lambda s: int(s.notna().sum()))
    result["reported_beams_round1"] = {t: int(counts.get((1, t), 0)) for t in ("ssb", "csi")}
    return result


def table_md(results: dict) -> str:
    labels = [k for k in ("wnomp", "rflscm", "nerf2", "model_floor", "noise_floor", "trivial")
              if any(k in r for r in results.values())]  # fmt: skip
    head = (
        "| step | reported SSB / CSI-RS beams (round 1) | "
        + " | ".join(f"{lab} SSB all / chg, CSI all / chg" for lab in labels)
        + " |"
    )
    lines = [head, "|" + " --- |" * (2 + len(labels))]
    for step, r in results.items():
        cells = []
        for lab in labels:
            if lab not in r:
                cells.append("—")
                continue
            m = r[lab]["mae_db"]
            cells.append(" / ".join("—" if m[b][s] is None else f"{m[b][s]:.2f}" for b, s in ROWS))
        beams = r["reported_beams_round1"]
        lines.append(f"| {step} | {beams['ssb']} / {beams['csi']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    steps = list(results)
    for ax, (bt, title) in zip(axes, (("ssb", "SSB"), ("csi", "CSI-RS")), strict=True):
        for lab, style in (("wnomp", "o-"), ("rflscm", "s-"), ("nerf2", "^-"), ("model_floor", "k--"),
                           ("noise_floor", "k:"), ("trivial", "x-")):  # fmt: skip
            ys = [r[lab]["mae_db"][bt]["changed"] if lab in r else None for r in results.values()]
            if any(y is not None for y in ys):
                ax.plot(steps, [float("nan") if y is None else y for y in ys], style, label=lab)
        ax.set_title(f"{title} MAE on changed cells, round 2")
        ax.set_ylabel("MAE [dB]")
        ax.tick_params(axis="x", rotation=30)
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/b8"))
    parser.add_argument("--trace", type=Path, default=default_scenario_path())
    parser.add_argument("--steps", default=",".join(STEPS))
    parser.add_argument("--rflscm", default="", help="steps at which to train RF-LSCM (quick), comma separated")
    parser.add_argument("--nerf2", default="", help="steps at which to train NeRF²-LSCM (quick), comma separated")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    store = args.out / "b8.json"
    results = json.loads(store.read_text()) if store.is_file() else {}
    for step in args.steps.split(","):
        neural = [m for m, steps in (("rflscm", args.rflscm), ("nerf2", args.nerf2)) if step in steps.split(",")]
        print(f"B8 step {step} …", flush=True)
        results[step] = {**results.get(step, {}), **run_step(step, args.trace, args.out, neural, args.seed)}
        store.write_text(json.dumps(results, indent=1))
    ordered = {s: results[s] for s in STEPS if s in results}
    (args.out / "b8.md").write_text(table_md(ordered))
    plot(ordered, args.out / "b8.png")
    print(table_md(ordered))


if __name__ == "__main__":
    main()
