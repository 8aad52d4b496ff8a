#!/usr/bin/env bash
# Set up ./.venv (created or reused) and run the main job end to end:
#   model -> collect -> summary -> fit -> predict (held-out data) -> compare with the truth.
# Outputs go to runs/demo/ (override with DEMO_OUT=...).
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/setup.sh"
OUT="${DEMO_OUT:-runs/demo}"
mkdir -p "$OUT"
T=".venv/bin/tensegrity"
echo "== 1. model: the paper's icosahedron with non-uniform parameters (seed 3), and the robot"
$T model ico --preset paper-nonuniform --seed 3 --out "$OUT/ico.xml"
$T model ico --preset robot --out "$OUT/robot.xml"
echo "== 2. collect: 10 trajectories x 1000 steps with pushes every 100 steps; a held-out test set"
$T collect --model "$OUT/ico.xml" --episodes 10 --steps 1000 --seed 1 --push-every 100 --out "$OUT/train.npz"
$T collect --model "$OUT/ico.xml" --episodes 5 --steps 2000 --seed 2 --push-every 100 --out "$OUT/test.npz"
$T collect --model "$OUT/robot.xml" --episodes 2 --steps 2000 --seed 1 --out "$OUT/robot.npz"
echo "== 3. summary"
$T summary "$OUT/train.npz"
$T summary "$OUT/robot.npz"
echo "== 4. fit: 54 parameters + inertias by least squares (pushes in newtons fix the scale)"
$T fit "$OUT/train.npz" --model "$OUT/ico.xml" --out "$OUT/ico.json" --quiet
echo "== 5. predict: free-run the identified model on the held-out trajectories"
$T predict "$OUT/test.npz" --identified "$OUT/ico.json" --plot "$OUT/error.png"
echo "== 6. the identified parameters against the plant's ground truth"
.venv/bin/python examples/compare_with_truth.py "$OUT/ico.json" --preset paper-nonuniform --seed 3
echo "outputs in $OUT/"
