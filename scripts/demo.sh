#!/usr/bin/env bash
# Set up ./.venv (created or reused) and run the main job end to end:
#   the paper's icosahedron identified to rounding error, then the robot:
#   collect -> fit with the effect search -> diagnose -> train on the twin -> gap on the plant,
#   ending with a video of the policy on the twin beside the plant and its learning curve.
# Outputs go to runs/demo/ (override with DEMO_OUT=...). The training budget is one variable:
# DEMO_TIMESTEPS (default: tensegrity train's own default, the budget at which policies trained
# on the twin transfer); DEMO_TRAIN_ARGS adds options to the training (e.g. "--envs 256").
# DEMO_VIDEO_EVERY: one video frame every K control steps (default 10: a 5x time-lapse at 25 fps;
# offscreen rendering on a CPU is the slow part). Every step's wall clock is printed at the end.
set -euo pipefail
T_START=$SECONDS
source "$(dirname "${BASH_SOURCE[0]}")/setup.sh"
OUT="${DEMO_OUT:-runs/demo}"
STEPS="${DEMO_TIMESTEPS:-}"
EVERY="${DEMO_VIDEO_EVERY:-10}"
mkdir -p "$OUT"
T=".venv/bin/tensegrity"
STEP_NAMES=("setup (.venv)")
STEP_TIMES=($((SECONDS - T_START)))

timed() {  # timed NAME COMMAND...: run it, keep its wall clock
    local name="$1" t0=$SECONDS
    shift
    "$@"
    STEP_NAMES+=("$name")
    STEP_TIMES+=($((SECONDS - t0)))
    echo "   ($name: $((SECONDS - t0)) s)"
}

# beside NAME COMMAND...: run it in the background (the twin trains on one core; these take the
# other), its output into $OUT/NAME.log and its wall clock into $OUT/NAME.seconds, shown by
# `shown` once it is done
beside() {
    local name="$1"
    shift
    ( t0=$SECONDS; "$@"; rc=$?; echo $((SECONDS - t0)) > "$OUT/$name.seconds"
      echo "   (${name//_/ }: $((SECONDS - t0)) s, beside the training)"; exit $rc ) > "$OUT/$name.log" 2>&1 &
    BESIDE+=("$name:$!")
}
BESIDE=()
shown() {
    local entry name pid
    for entry in "${BESIDE[@]}"; do
        name="${entry%%:*}" pid="${entry##*:}"
        wait "$pid" || { cat "$OUT/$name.log"; echo "demo: step '${name//_/ }' failed" >&2; exit 1; }
        echo "== ${name//_/ }"
        cat "$OUT/$name.log"
        STEP_NAMES+=("${name//_/ } (beside)")
        STEP_TIMES+=("$(cat "$OUT/$name.seconds")")
    done
}

paper() {
    $T model ico --preset paper-nonuniform --seed 3 --out "$OUT/ico.xml"
    $T collect --model "$OUT/ico.xml" --episodes 10 --steps 1000 --seed 1 --push-every 100 --out "$OUT/ico.npz" --quiet
    $T fit "$OUT/ico.npz" --model "$OUT/ico.xml" --out "$OUT/ico.json" --quiet
    .venv/bin/python examples/compare_with_truth.py "$OUT/ico.json" --preset paper-nonuniform --seed 3
}

collect_robot() {
    $T model ico --preset robot --out "$OUT/robot.xml"
    $T collect --model "$OUT/robot.xml" --episodes 10 --steps 2000 --seed 0 --push-every 200 --out "$OUT/robot.npz" --quiet
    $T collect --model "$OUT/robot.xml" --episodes 4 --steps 1000 --seed 1 --push-every 200 --out "$OUT/held.npz" --quiet
}

echo "== 2. the robot: 10 rollouts of 2 s (20 s of robot time) (random cable commands, pushes) and 4 held-out ones"
timed "collect (robot)" collect_robot
echo "== 3. fit with the effect search: what does the spring-rod model lack?"
timed "fit --effects auto" $T fit "$OUT/robot.npz" --model "$OUT/robot.xml" --effects auto --out "$OUT/robot.json" --quiet
echo "== 5. train PPO on the identified twin (${STEPS:-the default number of} steps; MuJoCo is never stepped);"
echo "   beside it, on the other core: 4. diagnose on the held-out rollouts (report in $OUT/diagnose/) and"
echo "   1. the paper's icosahedron (non-uniform, seed 3): 54 parameters + inertias from 10 x 1000 steps"
beside "4._diagnose" $T diagnose "$OUT/held.npz" --identified "$OUT/robot.json" --out "$OUT/diagnose"
beside "1._paper_icosahedron" paper
# shellcheck disable=SC2086  # DEMO_TRAIN_ARGS is a list of options
timed "train on the twin" $T train --identified "$OUT/robot.json" ${STEPS:+--timesteps "$STEPS"} --seeds 0 \
    --out "$OUT/train" --quiet ${DEMO_TRAIN_ARGS:-}
shown
gap_json() {
    $T gap --identified "$OUT/robot.json" --policy "$OUT/train/seed_0/policy.zip" --episodes 3 \
        --video "$OUT/video" --video-every "$EVERY" --json --quiet > "$OUT/gap.json"
}

echo "== 6. the gap: the policy on the twin and on the plant, a random policy on the plant; videos"
timed "gap on the plant (+ videos)" gap_json
.venv/bin/python - "$OUT/gap.json" <<'PY'
import json, sys
g = json.load(open(sys.argv[1]))
for k in ("twin", "plant", "random_plant"):
    print(f"   {k:<13} progress {g[k]['progress_m']:+.3f} m per episode, return {g[k]['return']:+.1f}")
ol = g["open_loop"]["at"]
print(f"   open loop: centres of mass {ol.get('1s')} m apart after 1 s, {ol.get('20s')} m after 20 s")
p = g["plant"]["progress_m"]
print(f"   the policy {'rolls' if p >= 0.5 else 'does not roll'} >= 0.5 m per episode on the plant ({p:.3f} m)")
PY
echo "== outputs in $OUT/"
echo "   the twin (left) beside the plant (right): $OUT/video/twin_plant.mp4"
echo "   learning curve: $OUT/train/seed_0/learning_curve.png (progress.csv beside it)"
echo "== wall clock per step"
for i in "${!STEP_NAMES[@]}"; do
    printf "   %-30s %5d s\n" "${STEP_NAMES[$i]}" "${STEP_TIMES[$i]}"
done
printf "   %-30s %5d s\n" "total" $((SECONDS - T_START))
