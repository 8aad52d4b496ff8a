"""The diagnosis as a report: figures (matplotlib) and a Markdown text of a
:func:`identified.diagnose.diagnose` result."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from identified.dataset import atomic_write

__all__ = ["write_report"]


def write_report(result: dict[str, Any], out_dir: str | os.PathLike) -> list[str]:
    """Write the figures (PNG) and ``report.md`` of a :func:`diagnose` result into ``out_dir``.

    Figures: the residual against time (first episode, per rod), the residual against its
    best-correlated candidate feature, the free-run error before and after the added effects.
    Every file is written atomically (temporary file, then rename).  Returns the paths written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = os.path.abspath(os.fspath(out_dir))
    os.makedirs(out, exist_ok=True)
    paths: list[str] = []

    def save(fig, name: str) -> str:
        p = os.path.join(out, name)
        atomic_write(p, lambda fh: fig.savefig(fh, format="png", dpi=100), binary=True)
        plt.close(fig)
        paths.append(p)
        return name

    figs = {}
    ts = (result.get("plot_data") or {}).get("residual_time") or {}
    if ts.get("t"):
        fig, axes = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True, constrained_layout=True)
        for rod, f, t in zip(ts["rods"], ts["force"], ts["torque"]):
            axes[0].plot(ts["t"], _nan(f), lw=0.8, label=rod)
            axes[1].plot(ts["t"], _nan(t), lw=0.8, label=rod)
        axes[0].set_ylabel("|force residual| (N)")
        axes[1].set_ylabel("|torque residual| (N m)")
        axes[1].set_xlabel("time (s), episode 0")
        axes[0].legend(fontsize=7, ncol=3)
        for ax in axes:
            ax.set_yscale("log")
            ax.grid(True, which="both", alpha=0.3)
        fig.suptitle("one-step residual against time")
        figs["time"] = save(fig, "residual_time.png")
    sc = (result.get("plot_data") or {}).get("feature") or {}
    if sc.get("x"):
        fig, ax = plt.subplots(figsize=(6, 4.5), constrained_layout=True)
        ax.scatter(_nan(sc["x"]), _nan(sc["y"]), s=3, alpha=0.4)
        ax.set_xlabel(f"feature {sc['name']} (N or N per unit parameter)")
        ax.set_ylabel("residual row (N; torque / half-length)")
        corr = sc.get("corr")
        ax.set_title(f"residual against its best-correlated feature (r = {corr:.3f})" if corr is not None
                     else "residual against its best-correlated feature")
        ax.grid(True, alpha=0.3)
        figs["feature"] = save(fig, "residual_feature.png")
    fr = result.get("free_run") or {}
    if fr.get("time_s"):
        fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
        if result.get("added"):
            ax.semilogy(fr["time_s"], np.maximum(_nan(fr["before"]), 1e-18), label="before (no added effects)")
        ax.semilogy(fr["time_s"], np.maximum(_nan(fr["after"]), 1e-18),
                    label=f"after ({', '.join(result['added'])})" if result.get("added") else "model")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("position error (m)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
        ax.set_title("free-run error, mean over rods and episodes")
        figs["free_run"] = save(fig, "free_run_error.png")

    text = _report_text(result, figs)
    p = os.path.join(out, "report.md")
    atomic_write(p, lambda fh: fh.write(text))
    paths.append(p)
    return paths


#: what each reason of ``explained_by`` says, in words
EXPLAINED_BY = {"rounding": "the one-step residual is at rounding level", "white": "the residual is white (Ljung-Box)",
                "improved": "the added effects cut the free-run error at least 5x"}


def _report_text(r: dict[str, Any], figs: dict[str, str]) -> str:
    f = lambda v, spec=".3g": "n/a" if v is None else format(v, spec)
    L = ["# Diagnosis of the identified model", ""]
    verdict = {"partial": "partly explained"}.get(r["explained"], "explained" if r["explained"] else "NOT explained")
    why = EXPLAINED_BY
    missing = r.get("unexplained_by") or []
    if missing:
        L.append(f"**Verdict: the residual is {verdict}**: "
                 + ", ".join(f"{c['name']} removes {c['score_held_out']:.1%}" for c in missing)
                 + " of it on data its coefficients were not fitted on"
                 + (f" (although {'; '.join(why[x] for x in r['explained_by'])})." if r["explained_by"] else "."))
    else:
        L.append(f"**Verdict: the residual is {verdict}**"
                 + (f" ({'; '.join(why[x] for x in r['explained_by'])})." if r["explained_by"] else
                    ": it is structured and the model's effects do not account for it."))
    for p in r.get("partial_by") or []:
        L.append(f"- {p['effect']} leaves a clear signature on its rows: the {p['part']} residual there is "
                 f"{f(p['relative_inside'], '.1%')} of the recorded {p['part']}, against "
                 f"{f(p['relative_outside'], '.2g')} on the other rods.")
    L.append("")
    L.append(f"Rule: {r['explained_rule']}.")
    L.append("")
    d = r["data"]
    L.append(f"Data: {d['episodes']} episodes x {d['steps_per_episode']} steps (dt {d['dt']:g} s), "
             f"{d['instants']} instants analysed; accelerations by the {d['scheme']} difference; "
             f"integrator {d['integrator']}.")
    L += ["", "## Free-run error", "", f"Metric: {r['metric']}.", ""]
    added = ", ".join(r["added"]) or "none"
    L.append(f"- before (no added effects): **{f(r['error_before'])} m**")
    L.append(f"- after (added: {added}): **{f(r['error_after'])} m**")
    if r["error_before"] and r["error_after"] is not None and r["added"]:
        L.append(f"- ratio after / before: {r['error_after'] / r['error_before']:.3g}")
    if "free_run" in figs:
        L += ["", f"![free-run error]({figs['free_run']})"]
    L += ["", "k-step position error (m) of the model as it is, from recorded states:", ""]
    L.append("| k | position error (m) | quaternion error |")
    L.append("|---|---|---|")
    for k, v in r["k_step"]["after"].items():
        L.append(f"| {k} | {f(v and v['pos'])} | {f(v and v['quat'])} |")
    os_ = r["one_step"]
    L += ["", "## One-step residual", "", f"Definition: {os_['definition']}.", "",
          (f"RMS over all rods: force {', '.join(f(x) for x in os_['force_rms'])} N (x, y, z), "
          f"torque {', '.join(f(x) for x in os_['torque_rms'])} N m (rod frame x, y, z); relative to the recorded "
          f"wrench: force {f(os_['relative']['force'])}, torque {f(os_['relative']['torque'])}."), "",
          "| rod | force RMS x, y, z (N) | torque RMS x, y, z (N m) |", "|---|---|---|"]
    for p in os_["per_rod"]:
        L.append(f"| {p['rod']} | {', '.join(f(x) for x in p['force_rms'])} | {', '.join(f(x) for x in p['torque_rms'])} |")
    L += ["", f"Worst rod: {os_['worst_rod']}."]
    for e in os_.get("effect_rows") or []:
        L += ["", (f"On the rods {e['effect']} acts on ({e['region']}, {e['fraction']:.1%} of the rod-instants) the "
                   f"residual is {f(e['inside']['force'])} of the recorded force and {f(e['inside']['torque'])} of the "
                   f"recorded torque; on the other rods {f(e['outside']['force'])} and {f(e['outside']['torque'])}.")]
        about = e["inside"].get("torque_about_contact_point")
        if about is not None:
            L[-1] += (f" About the contact point (the residual torque less the residual force's moment) the torque "
                      f"residual is {f(about)} of the recorded torque: the rest is the moment of a force at the "
                      f"contact that the law misses.")
    if "time" in figs:
        L += ["", f"![residual against time]({figs['time']})"]
    L += ["", "## Where: by region of state", "",
          "| region | share | force RMS in / out (N) | torque RMS in / out (N m) |", "|---|---|---|---|"]
    for k, v in r["regions"].items():
        if not v.get("available"):
            L.append(f"| {v['description']} | n/a | {v.get('reason', '')} | |")
            continue
        L.append(f"| {v['description']} | {v['fraction']:.1%} | {f(v['force_rms_in'])} / {f(v['force_rms_out'])} | "
                 f"{f(v['torque_rms_in'])} / {f(v['torque_rms_out'])} |")
    w = r["whiteness"]
    L += ["", "## Statistics", "",
          (f"Whiteness: {w['test']}: {'white' if w['white'] else 'not white'}; smallest p-value {f(w['min_p'])}, "
          f"{f(w['fraction_rejected'], '.0%') if w['fraction_rejected'] is not None else 'n/a'} of the rod/dof series "
          f"reject at 1 %, median Q / dof {f(w['median_Q_per_dof'])} (1 for white noise).")]
    ic = r["input_correlation"]
    for k, v in ic.items():
        if v.get("corr") is None:
            L.append(f"- correlation with {k}: n/a ({v.get('reason', '')})")
        else:
            L.append(f"- largest correlation with {k}: {v['corr']:+.3f} (rod {v['rod']} {v['dof']} with {v['input']})")
    L += ["", "## Candidate effects", "", f"Score: {r['score_rule']}.", "",
          "| effect | held out | score | unexplained | alone | parameters | best feature (corr) |",
          "|---|---|---|---|---|---|---|"]
    for c in r["candidates"]:
        bf = f"{c['best_feature']} ({f(c['max_abs_corr'])})" if c["best_feature"] else "n/a"
        if c.get("note"):
            bf += f"; {c['note']}"
        L.append(f"| {c['name']} | {f(c.get('score_held_out'), '.4f')} | {f(c['score'], '.4f')} | "
                 f"{f(c['unexplained'])} | {f(c['score_alone'])} | {c['n_params']} | {bf} |")
    for s in r["skipped"]:
        L.append(f"| {s['name']} | skipped | | | | | {s['reason']} |")
    if r["candidates"]:
        top = r["candidates"][0]
        held = top.get("score_held_out")
        L += ["", (f"The best candidate is **{top['name']}**: adding it would remove "
                  f"{f(top['score'], '.1%') if top['score'] is not None else 'n/a'} of the residual, "
                  f"{f(held, '.1%') if held is not None else 'n/a'} on data its coefficients were not fitted on.")]
    if "feature" in figs:
        L += ["", f"![residual against its best-correlated feature]({figs['feature']})"]
    return "\n".join(L) + "\n"


def _nan(v: list) -> np.ndarray:
    return np.array([np.nan if x is None else x for x in v], dtype=float)
