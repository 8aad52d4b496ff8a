#!/usr/bin/env bash
# Set up ./.venv (created or reused) and run the main job end to end:
#   the paper's icosahedron identified to rounding error, then the robot:
#   collect -> fit with the effect search -> diagnose -> train on the twin -> gap on the plant.
# Outputs go to runs/demo/ (override with DEMO_OUT=...); DEMO_TIMESTEPS sets the training budget
# (default 20000 control steps: minutes; the README says what 100k gives).
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/setup.sh"
OUT="${DEMO_OUT:-runs/demo}"
STEPS="${DEMO_TIMESTEPS:-20000}"
mkdir -p "$OUT"
T=".venv/bin/tensegrity"
echo "== 1. the paper's icosahedron (non-uniform, seed 3): 54 parameters + inertias from 10 x 1000 steps"
$T model ico --preset paper-nonuniform --seed 3 --out "$OUT/ico.xml"
$T collect --model "$OUT/ico.xml" --episodes 10 --steps 1000 --seed 1 --push-every 100 --out "$OUT/ico.npz" --quiet
$T fit "$OUT/ico.npz" --model "$OUT/ico.xml" --out "$OUT/ico.json" --quiet
.venv/bin/python examples/compare_with_truth.py "$OUT/ico.json" --preset paper-nonuniform --seed 3
echo "== 2. the robot: 10 rollouts of 3 s (random cable commands, pushes) and 4 held-out ones"
$T model ico --preset robot --out "$OUT/robot.xml"
$T collect --model "$OUT/robot.xml" --episodes 10 --steps 3000 --seed 0 --push-every 200 --out "$OUT/robot.npz" --quiet
$T collect --model "$OUT/robot.xml" --episodes 4 --steps 1000 --seed 1 --push-every 200 --out "$OUT/held.npz" --quiet
echo "== 3. fit with the effect search: what does the spring-rod model lack?"
$T fit "$OUT/robot.npz" --model "$OUT/robot.xml" --effects auto --out "$OUT/robot.json" --quiet
echo "== 4. diagnose on the held-out rollouts (report in $OUT/diagnose/)"
$T diagnose "$OUT/held.npz" --identified "$OUT/robot.json" --out "$OUT/diagnose"
echo "== 5. train PPO on the identified twin ($STEPS steps; MuJoCo is never stepped)"
$T train --identified "$OUT/robot.json" --timesteps "$STEPS" --seed 0 --envs 16 --rollout 4096 --out "$OUT/policy.zip" --quiet
echo "== 6. the gap: the policy on the twin and on the plant, a random policy on the plant"
$T gap --identified "$OUT/robot.json" --policy "$OUT/policy.zip" --episodes 3 --json > "$OUT/gap.json"
.venv/bin/python - "$OUT/gap.json" <<'PY'
import json, sys
g = json.load(open(sys.argv[1]))
for k in ("twin", "plant", "random_plant"):
    print(f"   {k:<13} progress {g[k]['progress_m']:+.3f} m per episode, return {g[k]['return']:+.1f}")
ol = g["open_loop"]["at"]
print(f"   open loop: centres of mass {ol.get('1s')} m apart after 1 s, {ol.get('20s')} m after 20 s")
PY
echo "outputs in $OUT/"
