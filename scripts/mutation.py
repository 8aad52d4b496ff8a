"""Mutation test: plant one plausible bug at a time, run the tests that should notice, count the
mutants killed, per module.

    nice -n 10 .venv/bin/python scripts/mutation.py [--group G ...] [--only N ...] [--list]

Each mutant is a one-line textual change with the fast tests of its module (a few seconds to a
minute each); the file is restored after every run (also on Ctrl-C).  A mutant "survives" when
those tests still pass with it: either the code is untested there or the mutant is equivalent.
A mutant whose original text is no longer in its file (the code moved) is reported ``STALE`` and
not counted.  Prints one line per mutant, then a table of mutants and kills per group.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: the fast tests of each group (pytest arguments)
TESTS = {
    "bad-input": ["tests/test_bad_input.py"],
    "diagnose": ["tests/test_diagnose.py"],
    "evaluate": ["tests/test_evaluate.py"],
    "search": ["tests/test_search_rules.py",
               "tests/test_effects.py::test_candidates_the_screen_cannot_tell_apart_are_ranked_by_their_free_run"],
    "effects": ["tests/test_effect_laws.py", "tests/test_effects.py", "-k",
                "by_hand or twin_cable_friction or laws or holds or classifies or implicit_drag"],
    "twin": ["tests/test_twin_actuation.py", "tests/test_twin.py", "-k",
             "actuat or batched_pure or chunked or vector_env_matches or clipped"],
    "vector": ["tests/test_vector_actions.py", "tests/test_twin.py", "-k", "vector or batched_pure"],
    "env-args": ["tests/test_bad_input.py", "-k", "fuzz_env or env_refuses"],
    "training": ["tests/test_train_metrics.py"],
    "gap": ["tests/test_gap_metrics.py"],
}

#: (group, file, original text, mutated text, what the bug would be[, its tests: default the group's])
MUTANTS = [
    # ------------------------------------------------------------------ bad input (guards)
    ("bad-input", "identified/fit/checks.py", "    if dof <= 0 or (not error_bars",
     "    if dof < -1e9 or (not error_bars", "a fit without residual degrees of freedom is accepted"),
    ("bad-input", "identified/fit/checks.py", "dof < MIN_DOF_PER_PARAMETER * free:", "dof < 0:",
     "error bars of a nearly exact fit printed as if estimable"),
    ("bad-input", "identified/fit/checks.py", "np.full(np.shape(v), np.nan) for k, v", "v for k, v",
     "not-estimable error bars kept"),
    ("bad-input", "identified/fit/checks.py", "j not in fixed and not th[j] > 0:",
     "j not in fixed and th[j] < -1e300:", "non-positive inertias kept"),
    ("bad-input", "identified/fit/checks.py", "        if not mass[i] > 0:", "        if mass[i] < -1e300:",
     "negative masses not warned"),
    ("bad-input", "identified/fit/checks.py", "if I[a] - others > max(margin, 1e-6 * others):", "if False:",
     "triangle inequality not checked"),
    ("bad-input", "identified/fit/checks.py", "    return 1.0 + 2.0 * sum(", "    return 1.0 + 0.0 * sum(",
     "overlap of weak-form windows ignored"),
    ("bad-input", "identified/fit/checks.py", "worst > ADAM_TOLERANCE:", "worst > 1e9:",
     "unconverged Adam accepted silently"),
    ("bad-input", "identified/model.py", "np.isfinite(model.dt) and model.dt > 0)",
     "np.isfinite(model.dt) and model.dt > -1)", "negative dt loaded"),
    ("bad-input", "identified/model.py", "if not model.inertia[i, a] > 0:", "if not model.inertia[i, a] > -1:",
     "negative inertia loaded"),
    ("bad-input", "identified/model.py", "if name not in known_names():", "if name is None:", "unknown effect loaded"),
    ("bad-input", "tensegrity_gym/paths.py", "        return os.path.samefile(a, b)", "        return False",
     "hard link to an input overwritten"),
    ("bad-input", "tensegrity_gym/paths.py", "if ipath is not None and _same_file(path, ipath):", "if False:",
     "output equal to an input overwritten"),
    ("bad-input", "identified/dataset.py", "off = np.abs(norm - 1.0) > tol", "off = (norm - 1.0) > tol",
     "quaternion norm below 1 accepted"),
    ("bad-input", "identified/fit/uncertainty.py", "cov_z = (lin.residual / dof) * (", "cov_z = (1.0) * (",
     "few-episode error bars without the residual variance"),
    ("bad-input", "tensegrity_gym/envs/vector.py",
     "z_range = e.healthy_z_range if e.terminate_when_unhealthy else None", "z_range = e.healthy_z_range",
     "vector env ignores terminate_when_unhealthy=False"),
    ("bad-input", "tensegrity_gym/collect.py", "            if caught.messages:", "            if False:",
     "MuJoCo instability recorded silently"),
    ("bad-input", "tensegrity_gym/limits.py", "if nbytes > MEMORY_SHARE * avail:", "if nbytes > 1e30 * avail:",
     "collection too large for memory started"),
    ("bad-input", "tensegrity_gym/options.py", "        if v < minimum:", "        if v < minimum - 1:",
     "zero steps/durations accepted"),
    ("bad-input", "identified/jsonsafe.py", "isinstance(obj, float) and not math.isfinite(obj):",
     "isinstance(obj, float) and False:", "NaN written into JSON"),
    ("bad-input", "tensegrity_gym/envs/tensegrity_ico_v0.py", "            if not np.isfinite(w):",
     "            if False:", "NaN reward weight accepted"),
    # ------------------------------------------------------------------ diagnose
    ("diagnose", "identified/diagnose/__init__.py", 'mean = fr["pos_mean_after_start"]', 'mean = fr["pos_mean"]',
     "free-run error averaged over steps 0..H (the recorded start counted)",
     ["tests/test_diagnose.py", "-k", "free_run_error or clean_plant"]),
    ("diagnose", "identified/effects/ground_contact.py", "        return (depth > -margin).any(-1)",
     "        return (depth > -margin).all(-1)", "near-ground rods: both ends instead of either",
     ["tests/test_diagnose.py", "-k", "contact_rods"]),
    ("diagnose", "identified/effects/ground_contact.py", "def rows_affected(self, state: Any, ctx: Any, margin: float = 0.01)",
     "def rows_affected(self, state: Any, ctx: Any, margin: float = 0.02)", "near-ground margin 2 cm",
     ["tests/test_diagnose.py", "-k", "contact_rods"]),
    ("diagnose", "identified/diagnose/residual.py", "            self.masks[k][blk] = rows.reshape(E_, n_t, R).numpy()",
     "            self.masks[k][blk] = ~rows.reshape(E_, n_t, R).numpy()", "region mask inverted",
     ["tests/test_diagnose.py", "-k", "contact_rods or regions"]),
    ("diagnose", "identified/diagnose/__init__.py", "if r_in is None or r_in < PARTIAL_LEVEL:",
     "if r_in is None or r_in <= PARTIAL_LEVEL:", "partial: level threshold exclusive",
     ["tests/test_diagnose.py", "-k", "verdict"]),
    ("diagnose", "identified/diagnose/__init__.py", "if r_out is not None and r_in < PARTIAL_RATIO * r_out:",
     "if r_out is not None and r_in < r_out:", "partial: no ratio to the other rods",
     ["tests/test_diagnose.py", "-k", "verdict"]),
    ("diagnose", "identified/diagnose/__init__.py", "if pairs and all(i >= PARTIAL_RATIO * o for i, o in pairs):",
     "if pairs and any(i >= PARTIAL_RATIO * o for i, o in pairs):", "partial: one episode enough",
     ["tests/test_diagnose.py", "-k", "verdict"]),
    ("diagnose", "identified/diagnose/__init__.py", '        return False, reasons, []',
     '        return bool(effect_rows), reasons, []', "not explained called explained when an effect has rows",
     ["tests/test_diagnose.py", "-k", "verdict"]),
    ("diagnose", "identified/diagnose/__init__.py", "eb > 0 and ea <= EXPLAINED_GAIN * eb))",
     "eb > 0 and ea < eb))", "improved: any gain instead of 5x", ["tests/test_diagnose.py", "-k", "rules"]),
    ("diagnose", "identified/diagnose/__init__.py", "    return all(v is not None and v < ROUNDING_LEVEL",
     "    return any(v is not None and v < ROUNDING_LEVEL", "rounding: force or torque instead of both",
     ["tests/test_diagnose.py", "-k", "rules or clean_plant"]),
    ("diagnose", "identified/diagnose/stats.py", "white = bool(m > 0 and min(pvals) > ALPHA / m)",
     "white = bool(m > 0 and min(pvals) > ALPHA / m ** 0)", "whiteness without Bonferroni",
     ["tests/test_diagnose.py", "-k", "whiteness"]),
    ("diagnose", "identified/diagnose/stats.py", "        q += rho * rho / (n - k)", "        q += rho * rho / n",
     "Ljung-Box weights",
     ["tests/test_diagnose.py", "-k", "ljung_box or whiteness"]),
    ("diagnose", "identified/diagnose/stats.py", "yc, xc = (y - y.mean(0)) * yv, (x - x.mean(0)) * xv",
     "yc, xc = (y - y.mean(0)) * yv, x * xv", "correlation of an uncentred input",
     ["tests/test_diagnose.py", "-k", "corr_matrix or input_correlation"]),
    ("diagnose", "identified/diagnose/stats.py", "if best is None or abs(c[a, b]) > abs(best[\"corr\"]):",
     "if best is None or c[a, b] > best[\"corr\"]:", "largest correlation by sign",
     ["tests/test_diagnose.py", "-k", "input_correlation"]),
    ("diagnose", "identified/diagnose/residual.py",
     'rel = {"force": _ratio(np.sqrt((force_rms ** 2).mean()), _rms(rf_[..., :3], (0, 1, 2))),',
     'rel = {"force": _ratio(force_rms.max(), _rms(rf_[..., :3], (0, 1, 2))),', "relative force: worst axis",
     ["tests/test_diagnose.py", "-k", "by_hand"]),
    ("diagnose", "identified/diagnose/residual.py", "    Z[m_idx[-1], [keep.index(k) for k in m_idx[:-1]]] = -1.0",
     "    Z[m_idx[-1], [keep.index(k) for k in m_idx[:-1]]] = 0.0", "scores without the total mass held"),
    ("diagnose", "identified/diagnose/residual.py", "FAST_QUANTILE = 0.9", "FAST_QUANTILE = 0.8",
     "fast region: top 20 %",
     ["tests/test_diagnose.py", "-k", "by_hand or regions"]),
    ("diagnose", "identified/diagnose/residual.py", "            outside = ~self.masks[region] & valid",
     "            outside = valid", "effect rows: the others include its own",
     ["tests/test_diagnose.py", "-k", "contact_rods"]),
    ("diagnose", "identified/diagnose/residual.py", '"force": _ratio(_rms(res[:, :3], None), _rms(ref[:, :3], None)),',
     '"force": _ratio(_rms(res[:, :3], None), _rms(ref, None)),', "effect rows: relative to the whole wrench",
     ["tests/test_diagnose.py", "-k", "contact_rods"]),
    ("diagnose", "identified/diagnose/residual.py", "                score = 1.0 - unexplained",
     "                score = 1.0 - rss / syy", "score against the residual, not the base refit"),
    # ------------------------------------------------------------------ evaluation
    ("evaluate", "identified/evaluate.py", '"pos_mean_after_start": float(pe[1:].mean())',
     '"pos_mean_after_start": float(pe.mean())', "free-run mean after the start counts step 0"),
    ("evaluate", "identified/evaluate.py", "    starts = np.arange(0, data.n_steps - steps + 1, stride)",
     "    starts = np.arange(0, data.n_steps - steps, stride)", "windows: the last start left out"),
    ("evaluate", "identified/evaluate.py", "data.pos[ep, t0 + k], axis=-1)", "data.pos[ep, t0 + k - 1], axis=-1)",
     "k-step error against the state one step early"),
    ("evaluate", "identified/evaluate.py", "        ep, t0 = np.divmod(pick, T - k + 1)",
     "        ep, t0 = np.divmod(pick, T - k)", "k-step starts mapped to the wrong episode"),
    ("evaluate", "identified/evaluate.py", "    nxt = (slice(None), slice(1, T + 1))",
     "    nxt = (slice(None), slice(0, T))", "one-step error against the same instant"),
    ("evaluate", "identified/evaluate.py", "        force = p.mass[:, None] * (ch.acc - terms.lin_acc)",
     "        force = ch.acc - terms.lin_acc", "residual force without the mass"),
    ("evaluate", "identified/evaluate.py", "                    keep &= ~rows", "                    pass",
     "one-step errors keep the contact rows"),
    ("evaluate", "identified/evaluate.py", "np.linalg.norm(q + q_ref, axis=-1))", "np.linalg.norm(q - q_ref, axis=-1))",
     "quaternion distance not sign-invariant"),
    ("evaluate", "identified/evaluate.py", "return self.inertial_force - self.terms.force,",
     "return self.inertial_force + self.terms.force,", "missing force with the wrong sign"),
    # ------------------------------------------------------------------ the effect search
    ("search", "identified/fit/pipeline.py", "one_before > ONE_STEP_FLOOR and one_before >= min_gain * one_after",
     "one_before > ONE_STEP_FLOOR and one_before >= one_after", "one-step rule: any cut"),
    ("search", "identified/fit/pipeline.py", "and np.isfinite(free_after) and free_after <= min_gain * free_before)",
     "and np.isfinite(free_after) and free_after <= free_before)", "one-step rule: free run may not grow at all"),
    ("search", "identified/fit/pipeline.py", "return bool(one_before > ONE_STEP_FLOOR and",
     "return bool(one_before > 0 and", "one-step rule: no floor"),
    ("search", "identified/fit/pipeline.py", "and np.isfinite(free_after) and free_after",
     "and True and free_after", "one-step rule: a diverged free run accepted"),
    ("search", "identified/fit/pipeline.py", "or (first_err > 0 and last_err <= first_err / 5)",
     "or (first_err > 0 and last_err < first_err)", "explained: any gain instead of 5x"),
    ("search", "identified/fit/pipeline.py", "return bool((relative is not None and relative < ROUNDING)",
     "return bool((relative is not None and relative <= ROUNDING)", "explained: rounding threshold inclusive"),
    ("search", "identified/fit/pipeline.py", "                or first_err == 0)", "                or False)",
     "explained: nothing to explain is not explained"),
    ("search", "identified/fit/pipeline.py", "before >= max(min_gain * after, FREE_RUN_FLOOR))",
     "before >= max(after, FREE_RUN_FLOOR))", "free-run rule: any cut"),
    ("search", "identified/fit/pipeline.py", "before >= max(min_gain * after, FREE_RUN_FLOOR))",
     "before >= min_gain * after)", "free-run rule: no rounding floor"),
    ("search", "identified/fit/pipeline.py", "np.isfinite(v) and v <= min_gain * top and v < 0.99 * base_screen]",
     "np.isfinite(v) and v <= top and v < 0.99 * base_screen]", "judge: only the best screen is run"),
    # ------------------------------------------------------------------ effects
    ("effects", "identified/effects/quadratic_drag.py", "        v_b = matrix_apply_transpose(rot, state.vel)",
     "        v_b = state.vel", "quadratic drag on world axes"),
    ("effects", "identified/effects/quadratic_drag.py", "        axes = rot.transpose(-1, -2)",
     "        axes = rot", "quadratic drag forces along the wrong axes"),
    ("effects", "identified/engine/engine.py",
     "            ang_acc_b = ang_acc_b * inertia / (inertia + self.dt * b_rot.unsqueeze(-1))",
     "            ang_acc_b = ang_acc_b * inertia[..., :1] / (inertia[..., :1] + self.dt * b_rot.unsqueeze(-1))",
     "implicit rotational damping with the transverse inertia on every axis"),
    ("effects", "identified/engine/engine.py",
     "            lin_acc = lin_acc * (m / (m + self.dt * b_lin)).unsqueeze(-1)",
     "            lin_acc = lin_acc * (m / (m + b_lin)).unsqueeze(-1)", "implicit damping without dt"),
    ("effects", "identified/effects/linear_drag.py",
     "            angvel = matrix_apply(ctx.rot, ctx.angvel_body + ctx.dt * ctx.recorded_ang_acc_body)",
     "            angvel = matrix_apply(ctx.rot, ctx.angvel_body)", "implicit drag's torque at the start velocity"),
    ("effects", "identified/effects/cable_friction.py", "            clamp = ~slip & (r.abs() > F)",
     "            clamp = ~slip & (r.abs() > F) & False", "twin friction cables never slip"),
    ("effects", "identified/effects/cable_friction.py", "        return q.abs() < F.clamp_min(0.0), torch.sign(q)",
     "        return q.abs() < 0.0 * F, torch.sign(q)", "fit friction cables never stick"),
    ("effects", "identified/effects/cable_friction.py", "        return q.abs() < F.clamp_min(0.0), torch.sign(q)",
     "        return q.abs() < F.abs() + 1e300, torch.sign(q)", "fit friction cables never slip"),
    ("effects", "identified/effects/cable_friction.py", "        self._never_stuck = np.asarray(stuck) < min_rows",
     "        self._never_stuck = np.asarray(stuck) < 1", "a cable seen sticking a few times keeps its stick law"),
    ("effects", "identified/effects/cable_friction.py", "        return np.stack([slip, stick, stick | slip], 1)",
     "        return np.stack([stick, slip, stick | slip], 1)", "held parameters swapped (never slipped / stuck)"),
    ("effects", "identified/effects/cable_friction.py", "        return bool(np.all(self._never_stuck))",
     "        return bool(np.any(self._never_stuck))", "inert when one cable never sticks"),
    # (the final clamp of the sticking force is a no-op after the last pass's update: not a mutant)
    ("effects", "identified/effects/cable_friction.py", "            release = slip & (sign * q < F)",
     "            release = slip & (q.abs() < F)", "a slipping cable sticks again whatever way the stick law pulls"),
    # ------------------------------------------------------------------ twin physics
    ("twin", "tensegrity_gym/backends/twin_physics.py",
     "rest = rest_act if self._all_actuated else rest.index_copy(-1, self._act, rest_act)",
     "rest = rest_act if self._all_actuated else rest.index_copy(-1, torch.arange(self._act.numel()), rest_act)",
     "actuated rest lengths written into the first cables"),
    ("twin", "tensegrity_gym/backends/twin_physics.py",
     "        self._all_actuated = bool(np.array_equal(np.asarray(actuated_index), np.arange(engine.n_springs)))",
     "        self._all_actuated = len(actuated_index) > 0", "some cables actuated taken as all"),
    ("twin", "tensegrity_gym/backends/twin_physics.py",
     "            rest_act = motor_step(rest_act, target, self._speed, e.dt, self._lo, self._hi)",
     "            rest_act = motor_step(rest_act, target, self._speed, 2 * e.dt, self._lo, self._hi)",
     "motors twice as fast"),
    ("twin", "tensegrity_gym/backends/twin_physics.py",
     "        self.target[self._index(index)] = torch.minimum(torch.maximum(t, self._lo), self._hi)",
     "        self.target[self._index(index)] = t", "targets not clipped"),
    ("twin", "tensegrity_gym/backends/twin_physics.py", "        ra = self.rest[i][..., self._act]",
     "        ra = self.rest[i][..., : self._act.numel()]", "reset reads the first cables' rest lengths"),
    # ------------------------------------------------------------------ vector env
    ("vector", "tensegrity_gym/envs/vector.py", "        a = np.clip(a, -1.0, 1.0)", "        a = a",
     "actions not clipped"),
    ("vector", "tensegrity_gym/envs/vector.py", "            com[ok] = pos[good].mean(axis=1)",
     "            com[ok] = pos[good][:, 0]", "centre of mass of the first rod"),
    ("vector", "tensegrity_gym/envs/vector.py", "            self._elapsed[s] += 1", "            self._elapsed[s] += 2",
     "episode length counted twice"),
    ("vector", "tensegrity_gym/envs/vector.py", "            self._com[good] = com[ok]", "            pass",
     "centre of mass never updated"),
    ("vector", "tensegrity_gym/envs/vector.py",
     "        pos, quat, vel, angvel = ph.states_numpy()\n        quat = quat / np.sqrt(",
     "        pos, quat, vel, angvel = ph.states_numpy()\n        quat = quat * 1.01 / np.sqrt(",
     "stepped quaternions not normalised"),
    # ------------------------------------------------------------------ the env's arguments
    ("env-args", "tensegrity_gym/envs/tensegrity_ico_v0.py",
     "        if not (np.isfinite(reset_noise_scale) and 0 <= reset_noise_scale <= 1):",
     "        if True:", "every input refused"),
    ("env-args", "tensegrity_gym/envs/tensegrity_ico_v0.py",
     "        if not (np.isfinite(reset_noise_scale) and 0 <= reset_noise_scale <= 1):",
     "        if not (np.isfinite(reset_noise_scale) and 0 <= reset_noise_scale):", "reset noise above 1 accepted"),
    ("env-args", "tensegrity_gym/envs/tensegrity_ico_v0.py",
     "        if not (np.isfinite(lo_z) and np.isfinite(hi_z) and lo_z < hi_z):",
     "        if not (np.isfinite(lo_z) and np.isfinite(hi_z)):", "an empty healthy range accepted"),
    # ------------------------------------------------------------------ training
    ("training", "tensegrity_gym/training.py", 'self._dist[i] += float(info.get("x_velocity", 0.0)) * dt',
     'self._dist[i] += float(info.get("y_velocity", 0.0)) * dt', "progress along the wrong coordinate"),
    ("training", "tensegrity_gym/training.py", "                    self._dist[i] = 0.0\n",
     "                    pass\n", "progress never reset per episode"),
    ("training", "tensegrity_gym/training.py",
     'hp["n_steps"] = -(-min(int(self.rollout), int(self.timesteps)) // self.n_envs)',
     'hp["n_steps"] = min(int(self.rollout), int(self.timesteps)) // self.n_envs',
     "rollout rounded down with envs that do not divide it"),
    ("training", "tensegrity_gym/training.py", 'hp["batch_size"] = min(int(hp["batch_size"]), hp["n_steps"] * self.n_envs)',
     'hp["batch_size"] = int(hp["batch_size"])', "mini-batch larger than the rollout"),
    ("training", "tensegrity_gym/training.py",
     'hp["learning_starts"] = min(int(hp["learning_starts"]), int(self.timesteps) // 10)',
     'hp["learning_starts"] = int(hp["learning_starts"])', "SAC waits longer than a short run"),
    ("training", "tensegrity_gym/training.py", "                    self.episodes += 1",
     "                    self.episodes += int(ep is not None)", "episodes without a Monitor record not counted"),
    # ------------------------------------------------------------------ gap
    ("gap", "tensegrity_gym/gap.py", 'return {"plant_over_twin": _ratio(plant["progress_m"], twin["progress_m"]),',
     'return {"plant_over_twin": _ratio(twin["progress_m"], plant["progress_m"]),', "plant/twin ratio inverted"),
    ("gap", "tensegrity_gym/gap.py", '"plant_over_random": _ratio(plant["progress_m"], random_plant["progress_m"])}',
     '"plant_over_random": _ratio(plant["progress_m"], twin["progress_m"])}', "plant/random ratio over the twin"),
    ("gap", "tensegrity_gym/gap.py", "    return float(a / b) if b > 0 and np.isfinite(a / b) else None",
     "    return float(a / b) if b != 0 and np.isfinite(a / b) else None", "ratio over a negative progress"),
    ("gap", "tensegrity_gym/gap.py", "            progress[k] = x[k] - x0[k]", "            progress[k] = x[k]",
     "progress from the origin, not the start"),
    ("gap", "tensegrity_gym/gap.py", "            ret[k] += float(rew[k])", "            ret[k] = float(rew[k])",
     "return of the last step only"),
    ("gap", "tensegrity_gym/gap.py", "        n = min(len(cp), len(ct) - (1 if twin.diverged[k] else 0))",
     "        n = min(len(cp), len(ct))", "open loop: the twin's diverged instant kept"),
    ("gap", "tensegrity_gym/gap.py", "            active &= ~np.isnan(actions[:, t]).any(axis=1)",
     "            active &= ~np.isnan(actions[:, t]).all(axis=1)", "open loop: a partly NaN row played"),
]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--group", nargs="*", default=None, help=f"groups to run (default all: {', '.join(TESTS)})")
    ap.add_argument("--only", type=int, nargs="*", default=None, help="run these mutants only (indices)")
    ap.add_argument("--list", action="store_true", help="list the mutants and exit")
    args = ap.parse_args()
    chosen = [(k, m) for k, m in enumerate(MUTANTS)
              if (args.group is None or m[0] in args.group) and (args.only is None or k in args.only)]
    if args.list:
        for k, (group, rel, _, _, what, *_) in chosen:
            print(f"{k:3d} {group:<10} {rel}: {what}")
        return 0
    table: dict[str, list[int]] = {}
    env = dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
    for k, (group, rel, old, new, what, *tests) in chosen:
        path = ROOT / rel
        text = path.read_text()
        if text.count(old) != 1:
            print(f"{k:3d} STALE    {group:<10} {rel}: the original text is not there exactly once ({what})",
                  flush=True)
            continue
        t0 = time.perf_counter()
        try:
            path.write_text(text.replace(old, new))
            r = subprocess.run([sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider",
                                *(tests[0] if tests else TESTS[group])], check=False, cwd=ROOT, capture_output=True, text=True, env=env)
        finally:
            path.write_text(text)
        dead = r.returncode != 0
        counts = table.setdefault(group, [0, 0])
        counts[0] += 1
        counts[1] += dead
        print(f"{k:3d} {'killed  ' if dead else 'SURVIVED'} {group:<10} ({time.perf_counter() - t0:.0f} s) "
              f"{rel}: {what}", flush=True)
    total = [sum(c[0] for c in table.values()), sum(c[1] for c in table.values())]
    print("\n| group | mutants | killed |\n| --- | --- | --- |")
    for group, (n, dead) in table.items():
        print(f"| {group} | {n} | {dead} |")
    print(f"| all | {total[0]} | {total[1]} ({total[1] / max(total[0], 1):.0%}) |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
