#!/usr/bin/env bash
# Regenerate identified/data/robot.json: the identified model the twin loads without model=
# (gym.make("TensegrityIco-v0", backend="identified")). Never edit that file by hand; run
#
#     scripts/make_shipped_model.sh            # or: SHIP_WORK=/some/dir scripts/make_shipped_model.sh
#
# It runs the project's own commands, nothing else:
#   1. tensegrity model ico --preset robot      the plant (MJCF)
#   2. tensegrity collect ...                   rollouts of the plant: random initial states, smooth
#                                               random cable commands, random 50 N pushes
#   3. tensegrity fit ...                       the identified parameters
# and then replaces the absolute MJCF path that `fit` records in "source_model" by
# "preset:ico/robot", which the twin resolves on any machine by rebuilding the robot preset's MJCF
# (tensegrity_gym.models.build_model("ico", "robot"); used for geometry, motors, the nominal
# keyframe and drawing only, never for parameters).
#
# The fit runs the effect search (--effects auto): on the robot's data it adds pyramid_contact (the
# rods' capsules on the ground plane, identified from the data, never read from the MJCF), which
# leaves the spring-rod parameters exact (the equations of rods away from the ground are
# contact-free) and lets the twin stand and roll. The scale comes from the pushes, recorded in
# newtons.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
T="${TENSEGRITY:-.venv/bin/tensegrity}"
PY="${PYTHON_BIN:-.venv/bin/python}"
WORK="${SHIP_WORK:-$(mktemp -d)}"
OUT=identified/data/robot.json
mkdir -p "$WORK" identified/data

echo "== 1. model: the ico/robot preset"
$T model ico --preset robot --out "$WORK/robot.xml"
echo "== 2. collect: 10 episodes x 3000 steps (3 s each: long enough for the random commands to roll it), a push every 200 steps"
$T collect --model "$WORK/robot.xml" --episodes 10 --steps 3000 --seed 0 --push-every 200 \
    --out "$WORK/robot.npz"
echo "== 3. fit: one K, c per cable and one M, I per rod, and the effects the data show"
$T fit "$WORK/robot.npz" --model "$WORK/robot.xml" --effects auto --out "$WORK/robot.json" --quiet
echo "== 4. source_model -> preset:ico/robot (resolves on a fresh clone)"
$PY - "$WORK/robot.json" "$OUT" <<'EOF'
import sys
from identified.model import load_model, save_model

model = load_model(sys.argv[1])
model.source_model = "preset:ico/robot"
save_model(sys.argv[2], model)  # atomic
print(f"wrote {sys.argv[2]}")
EOF
