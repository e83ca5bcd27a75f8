"""B8 — antenna-adjustment MAE as measurement realism grows, one effect at a time and then all (issue 12).

Every step re-measures the same trace (``--scenario``, default the shipped munich scenario; the
``rflscm simulate --from-trace`` semantics, no tracing) into ``<out>/b8/<step>`` (kept between runs),
then scores round 2 on the whole scenario: WNOMP (settings chosen per step on held-aside round-1
beams), RF-LSCM and NeRF²-LSCM (their preset, trained to the size's wall-time budget, as
``rflscm demo`` trains), the model floor (true APS through the nominal A′), the noise floor and the
trivial baseline.

Steps: ``ideal`` (2 dB noise on the expectation, every beam above −120 dBm, all traced points in
both rounds); ``reporting`` (SS-SINR detection, serving-cell top-4 CSI-RS); ``noise`` (faded samples
and the report error); ``array_error`` (per-element amplitude/phase errors of the true arrays);
``ue_sampling`` (random traced points, drawn anew per round); ``all`` (the field default).  Sizes:
``quick`` = the models' ``quick`` presets trained 3 minutes each (the demo's budget); ``full`` = the
``full`` presets and their step counts, for a GPU.
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from pathlib import Path
from typing import Any, Literal

import numpy as np

from rflscm.bench import BenchContext, register_bench
from rflscm.bench.harness import BenchSize, bench_size, model_config, scenario_path
from rflscm.bench.report import new_figure, save_figure
from rflscm.data import BEAM_TYPES
from rflscm.sim.field import FieldConfig

IDEAL = FieldConfig.ideal()
FULL = FieldConfig()
STEPS: dict[str, tuple[Literal["ideal", "field"], FieldConfig]] = {
    "ideal": ("ideal", IDEAL),
    "reporting": ("field", dataclasses.replace(IDEAL, ssb_detection="sinr", csi_serving_only=True, csi_top_n=4)),
    "noise": (
        "field",
        dataclasses.replace(
            IDEAL, fading=True, samples_per_grid=FULL.samples_per_grid, accuracy_sigma_db=FULL.accuracy_sigma_db
        ),
    ),
    "array_error": (
        "field",
        dataclasses.replace(
            IDEAL, array_amp_sigma_db=FULL.array_amp_sigma_db, array_phase_sigma_deg=FULL.array_phase_sigma_deg
        ),
    ),
    "ue_sampling": ("field", dataclasses.replace(IDEAL, positions="random")),
    "all": ("field", FULL),
}
"""Step → (regime, effects): the ideal regime, each effect of the field default alone, then all of them."""
NEURAL = ("rflscm", "nerf2")
BUDGET_S: dict[str, float | None] = {"tiny": None, "quick": 180.0, "full": None}
"""Training budget [s] of each neural model per step (None: the preset's step count)."""
ROWS = (("ssb", "all"), ("ssb", "changed"), ("csi", "all"), ("csi", "changed"))
FLOORS = (("model_floor", "oracle_mae_db"), ("noise_floor", "noise_floor_mae_db"), ("trivial", "trivial_mae_db"))


@register_bench("b8", "realism sweep: WNOMP, RF-LSCM, NeRF²-LSCM, floors and trivial, one field effect at a time")
def run(ctx: BenchContext) -> dict[str, Any]:
    return run_b8(ctx, bench_size(ctx.size))


def run_b8(ctx: BenchContext, size: BenchSize, steps: tuple[str, ...] = tuple(STEPS)) -> dict[str, Any]:
    trace, source = scenario_path(ctx)
    results = {step: run_step(ctx, size, trace, step) for step in steps}
    out: dict[str, Any] = {
        "size": size.describe(),
        "trace": str(trace),
        "source": source,
        "budget_s": BUDGET_S[size.name],
        "notes": __doc__.split("\n\n")[-1].strip(),
        "steps": results,
    }
    (Path(ctx.out_dir) / "b8.md").write_text(table_md(results))
    out["plots"] = [_plot(ctx, results)]
    return out


def measured(trace: Path, step: str, folder: Path) -> Path:
    """``trace`` re-measured in ``step``'s regime into ``folder`` (reused when it holds exactly that
    measurement: the same recorded simulation config; otherwise measured again, never silently stale)."""
    from rflscm.config import to_dict
    from rflscm.errors import RflscmError
    from rflscm.sim.remeasure import remeasure, trace_config

    regime, effects = STEPS[step]
    cfg = dataclasses.replace(trace_config(trace), measurements=regime, field_model=effects, name=f"b8-{step}")
    if (folder / "scenario.yaml").is_file():
        try:
            if to_dict(trace_config(folder)) == to_dict(cfg):
                return folder
        except RflscmError:  # an unreadable leftover is measured again
            pass
    shutil.rmtree(folder, ignore_errors=True)
    remeasure(trace, cfg, folder)
    return folder


def run_step(ctx: BenchContext, size: BenchSize, trace: Path, step: str) -> dict[str, Any]:
    """One step: WNOMP (selected settings), the neural models and the floors on the re-measured trace."""
    from rflscm.data import load_scenario
    from rflscm.eval import AdjustProtocol, fit_with_protocol, run_evaluation
    from rflscm.eval.cache import APSCache
    from rflscm.models import MODEL_REGISTRY
    from rflscm.models.wnomp import WNOMPModel
    from rflscm.models.wnomp_select import select_wnomp

    scenario = load_scenario(measured(trace, step, Path(ctx.out_dir) / "b8" / step))
    grid = size.grid()
    t0 = time.perf_counter()
    chosen, table = select_wnomp(scenario, grid, device=ctx.device)
    result: dict[str, Any] = {
        "wnomp_settings": dataclasses.asdict(chosen),
        "wnomp_selection_s": time.perf_counter() - t0,
        "wnomp_selection": table.to_dict(orient="records"),
    }
    models: list[tuple[str, Any]] = [("wnomp", WNOMPModel(chosen, grid, ctx.device))]
    models += [(m, MODEL_REGISTRY[m].build(neural_config(m, size), grid, ctx.device)) for m in NEURAL]
    for label, model in models:
        print(f"b8 {step}: {label} …", flush=True)  # a long benchmark (about an hour at quick size) shows where it is
        t0 = time.perf_counter()
        budget = BUDGET_S[size.name] if label in NEURAL else None
        fit = fit_with_protocol(model, scenario, AdjustProtocol(), budget_s=budget, progress=False)
        fit_s = time.perf_counter() - t0
        metrics = run_evaluation(APSCache(model), scenario, AdjustProtocol(), oracle="auto").metrics
        result[label] = {
            "mae_db": metrics["mae_db"],
            "bias_db": metrics["bias_db"],
            "fit_s": fit_s,
            "steps": fit.get("steps"),
        }
        for key, floor in FLOORS:
            result[key] = {"mae_db": metrics[floor]}
    counts = scenario.measurements.groupby(["round", "beam_type"])["rsrp_dbm"].apply(lambda s: int(s.notna().sum()))
    result["reported_beams_round1"] = {t: int(counts.get((1, t), 0)) for t in BEAM_TYPES}
    return result


def neural_config(model: str, size: BenchSize) -> Any:
    """The whole-scenario config of a neural model: its preset (as ``rflscm demo`` and ``train`` use it), or
    the tiny size's overrides in tests; the benchmark sizes' one-site step counts do not apply here."""
    return model_config(model, size, seed=0) if size.name == "tiny" else size.preset


def table_md(results: dict[str, Any]) -> str:
    """The Markdown table of BENCHMARKS.md: one row per step, each model's four MAEs (SSB all / changed, CSI-RS
    all / changed)."""
    labels = [
        k
        for k in ("wnomp", "rflscm", "nerf2", "model_floor", "noise_floor", "trivial")
        if any(k in r for r in results.values())
    ]
    head = "| step | reported SSB / CSI-RS beams, round 1 | " + " | ".join(labels) + " |"
    lines = [head, "|" + " --- |" * (2 + len(labels))]
    for step, r in results.items():
        cells = []
        for lab in labels:
            m = r[lab]["mae_db"] if lab in r else None
            cells.append(
                "—" if m is None else " / ".join("—" if m[b][s] is None else f"{m[b][s]:.2f}" for b, s in ROWS)
            )
        beams = r["reported_beams_round1"]
        lines.append(f"| {step} | {beams['ssb']} / {beams['csi']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _plot(ctx: BenchContext, results: dict[str, Any]) -> str:
    fig, axes = new_figure(ncols=2, width=5.5)
    steps = list(results)
    for ax, (bt, title) in zip(axes, (("ssb", "SSB"), ("csi", "CSI-RS")), strict=True):
        for lab, style in (
            ("wnomp", "o-"),
            ("rflscm", "s-"),
            ("nerf2", "^-"),
            ("model_floor", "k--"),
            ("noise_floor", "k:"),
            ("trivial", "x-"),
        ):
            ys = [r[lab]["mae_db"][bt]["changed"] if lab in r else None for r in results.values()]
            ax.plot(steps, [np.nan if y is None else y for y in ys], style, label=lab)
        ax.set_title(f"{title}: round-2 MAE on the changed cells")
        ax.set_ylabel("MAE [dB]")
        ax.tick_params(axis="x", rotation=30)
        ax.grid(alpha=0.3)
    axes[0].legend()
    return save_figure(fig, ctx, "b8_realism")
