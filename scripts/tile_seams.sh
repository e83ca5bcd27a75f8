#!/usr/bin/env bash
# The cost of the seams (issue 29, BENCHMARKS.md "Tiles: the cost of the seams"): a network small enough for one
# model, trained whole and in tiles, each scored on round 2 (adjust protocol), side by side.
# Usage: scripts/tile_seams.sh SCENARIO OUT_DIR TILE_SITES [RF-LSCM --set options...]
# Step mode (no --minutes) on one thread: deterministic and independent of the machine's load.
set -euo pipefail
scenario=$1 out=$2 tile_sites=$3
shift 3
mkdir -p "$out"
for model in wnomp rflscm; do
  extra=()
  [ "$model" = rflscm ] && extra=("$@")
  for tiles in 0 "$tile_sites"; do
    name=${model}_tiles${tiles}
    /usr/bin/time -v -o "$out/$name.time" rflscm --threads 1 train "$scenario" --model "$model" --tile-sites "$tiles" \
      --out "$out/$name.ckpt" --no-progress --device cpu --force ${extra[@]+"${extra[@]}"} 2>&1 | tee "$out/$name.train.log"
    rflscm --threads 1 evaluate "$out/$name.ckpt" "$scenario" --json "$out/$name.json" --device cpu --force \
      > "$out/$name.eval.log" 2>&1
  done
done
python - "$out" "$tile_sites" <<'PY'
import json, re, sys
from pathlib import Path
out, k = Path(sys.argv[1]), sys.argv[2]
print("| model | tiles | SSB all | SSB changed | CSI-RS all | CSI-RS changed | train wall [s] | peak RSS [GB] |")
print("|---|---|---|---|---|---|---|---|")
for model in ("wnomp", "rflscm"):
    for tiles in ("0", k):
        name = f"{model}_tiles{tiles}"
        m = json.loads((out / f"{name}.json").read_text())["mae_db"]
        t = (out / f"{name}.time").read_text()
        wall = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): (\S+)", t).group(1).split(":")
        secs = sum(float(x) * 60**i for i, x in enumerate(reversed(wall)))
        rss = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", t).group(1)) / 2**20
        label = "whole" if tiles == "0" else f"--tile-sites {tiles}"
        row = [m["ssb"]["all"], m["ssb"]["changed"], m["csi"]["all"], m["csi"]["changed"]]
        print(f"| {model} | {label} | " + " | ".join(f"{v:.2f}" for v in row) + f" | {secs:.0f} | {rss:.2f} |")
PY
