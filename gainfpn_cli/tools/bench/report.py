"""The bench's tables (results.md) and plots."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .points import MOTION_TARGET_PX, REFINED_TARGET_PX

#: The confidence is honest where k's actual error is within 25 % of the sigma_k it states (issue 21).
CALIBRATION_LOW, CALIBRATION_HIGH = 0.75, 1.25


def markdown(summary: dict) -> str:
    """The results as a Markdown table, one row per point."""
    m = summary["machine"]
    lines = [f"Measured by `gainfpn bench{' --quick' if summary['quick'] else ''}` in {summary['duration_s']:.0f} s "
             f"on {m['cpus']} CPUs ({m['processor']}, {m['platform']}, Python {m['python']})."]
    rows = [r for r in summary["points"] if r["kind"] != "motion" and r["group"] != "confidence"]
    if rows:  # a run of the confidence or motion_accuracy group alone has only its own table
        lines += ["", "| group | point | burst | residual FPN % (bound) | MSE before | MSE after | ratio | time s "
                  "(read / motion / solve / write) | peak RSS MB |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        burst = _burst(r["burst"])
        t = r.get("timings", {})
        stages = " / ".join(f"{t[k]:.2f}" for k in ("read_s", "motion_s", "solve_s", "write_s") if k in t)
        total = t.get("total_s", t.get("solve_s"))
        time_text = f"{total:.2f}" + (f" ({stages})" if stages and "total_s" in t else "") if total else ""
        if "parallel_speedup" in r:
            time_text = ", ".join(f"{k} {v:.2f}" for k, v in t["solve_by_workers_s"].items()) + \
                f"; speed-up {r['parallel_speedup']:.2f}x"
        fmt = lambda key, spec: format(r[key], spec) if r.get(key) is not None else ""  # noqa: E731
        bound = f" ({fmt('residual_bound_percent', '.2f')})" if r.get("residual_bound_percent") is not None else ""
        residual = "refused" if r.get("refused") else fmt("residual_fpn_percent", ".2f") + bound
        ratio = fmt("mse_ratio", ".1f")
        if r.get("frame_mse_ratio") is not None and r.get("estimated_percent", 100) < 99:  # planes turned away
            ratio += f" (frame {r['frame_mse_ratio']:.1f})"
        lines.append(f"| {r['group']} | {r['label']} | {burst} | {residual} | "
                     f"{fmt('mse_before', '.2f')} | {fmt('mse_after', '.2f')} | {ratio} | "
                     f"{time_text} | {r['peak_rss_mb']:.0f} |")
    motion = [r for r in summary["points"] if r["kind"] == "motion"]
    if motion:
        lines += ["", (f"Motion accuracy: each burst's worst frame, RMS trajectory error over the background, px, of "
                       f"the first estimate (as the default preset's; target {MOTION_TARGET_PX} px) and of the warps the "
                       f"scene solver refines from it against its model (target {REFINED_TARGET_PX} px)."), "",
                  ("| point | burst | scene | bursts (seeds) | median | max | over target | refined median | refined max "
                   "| over target | motion s per burst | refining s per burst |"),
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in motion:
            b, worst = r["burst"], np.array(r["motion_worst_px"])
            refined = np.array(r.get("refined_worst_px") or [np.nan])
            lines.append(f"| {r['label']} | {_burst(b)} | {b['scene']} | "
                         f"{len(worst)} ({b['seed']}-{b['seed'] + len(worst) - 1}) | {np.median(worst):.3f} | "
                         f"{worst.max():.3f} | {r['motion_over_target']} | {np.median(refined):.3f} | "
                         f"{refined.max():.3f} | {r.get('refined_over_target', '')} | {r['timings']['motion_s']:.2f} | "
                         f"{r['timings'].get('refine_s', float('nan')):.1f} |")
    lines += _confidence_table([r for r in summary["points"] if r["group"] == "confidence"])
    exponents = {r.get("fitted_time_exponent") for r in summary["points"]} - {None}
    if exponents:
        lines += ["", f"Time grows as (pixels x frames)^{exponents.pop():.2f} (balanced preset, least squares in log-log)."]
    return "\n".join(lines) + "\n"


def _burst(b: dict) -> str:
    """A burst as width x height x frames."""
    return f"{b['shape'][1]}x{b['shape'][0]}x{b['n_frames']}"


def _confidence_table(rows: list[dict]) -> list[str]:
    if not rows:
        return []
    lines = ["", "Confidence: per tenth of the written sigma_k, k's actual error (RMS) over the sigma_k it states "
             f"(RMS); 1 is honest, the target {CALIBRATION_LOW}-{CALIBRATION_HIGH} in every tenth. 'calibrated': "
             "sigma_k measured on two halves of the frames (6 fitted frames or more) or on the burst the scene "
             "model predicts (3-5, not on a CFA mosaic), else the solver's own.", "",
             "| point | burst | residual FPN % (bound) | MSE ratio | calibrated | tenths, lowest to highest sigma_k "
             "| outside target |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        burst = _burst(r["burst"])
        deciles = r.get("confidence_deciles") or []
        if r.get("refused") or not deciles:
            why = "refused" if r.get("refused") else "hold-out rejected: k = 1 written"
            lines.append(f"| {r['label']} | {burst} | {why} | | | | |")
            continue
        outside = sum(not CALIBRATION_LOW <= d <= CALIBRATION_HIGH for d in deciles)
        lines.append(f"| {r['label']} | {burst} | {r['residual_fpn_percent']:.2f} ({r['residual_bound_percent']:.2f}) "
                     f"| {r['mse_ratio']:.2f} | {'yes' if r.get('confidence_calibrated') else 'no'} | "
                     f"{' '.join(f'{d:.2f}' for d in deciles)} | {outside} |")
    return lines


def plot(summary: dict, out_dir: Path) -> list[Path]:
    """pareto.png, scaling.png and flow_error.png (those whose points were measured)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = summary["points"]
    written = []
    timed = [r for r in rows if r["kind"] == "pipeline" and r["group"] not in ("scaling_pixels", "scaling_frames")
             and not r.get("refused")]
    if timed:
        fig, ax = plt.subplots(figsize=(7, 4.5))
        for r in timed:
            star = r["group"] in ("preset", "reference")
            ax.scatter(r["timings"]["total_s"], r["residual_fpn_percent"], marker="*" if star else "o",
                       s=120 if star else 30, color="C1" if star else "C0")
            if star:
                ax.annotate(r["label"], (r["timings"]["total_s"], r["residual_fpn_percent"]), fontsize=7,
                            xytext=(4, 4), textcoords="offset points")
        ax.set(xscale="log", xlabel="wall time, end to end (s)", ylabel="residual gain FPN (%)",
               title="accuracy against time (stars: presets and the published form)")
        _plain_log(ax.xaxis)
        for r in rows:  # reference lines, labelled at the left edge (x in axes fraction, y in data)
            if r["kind"] in ("floor", "flat-field"):
                ax.axhline(r["residual_fpn_percent"], color="grey", ls="--", lw=0.8)
                ax.text(0.01, r["residual_fpn_percent"], r["label"], transform=ax.get_yaxis_transform(), fontsize=7,
                        color="grey", va="bottom")
        written.append(_save(fig, out_dir / "pareto.png"))
    scaling = [r for r in rows if r["group"] == "scaling_pixels"]
    if scaling:
        fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.8))
        for preset in sorted({r["preset"] for r in scaling}):
            sel = [r for r in scaling if r["preset"] == preset]
            a1.plot([r["megapixels"] for r in sel], [r["timings"]["total_s"] for r in sel], "o-", label=preset)
            a2.plot([r["megapixels"] for r in sel], [r["peak_rss_mb"] / 1024 for r in sel], "o-", label=preset)
        a1.set(xscale="log", yscale="log", xlabel="megapixels (8 frames)", ylabel="time (s)")
        a2.set(xscale="log", xlabel="megapixels (8 frames)", ylabel="peak RSS (GiB)")
        for axis in (a1.xaxis, a1.yaxis, a2.xaxis):
            _plain_log(axis)
        a1.legend()
        written.append(_save(fig, out_dir / "scaling.png"))
    flow = [r for r in rows if r["kind"] == "flow-error"]
    if flow:
        fig, ax = plt.subplots(figsize=(6, 3.8))
        ax.plot([r["flow_error_px"] for r in flow], [r["mse_ratio"] for r in flow], "o-")
        ax.axhline(1.0, color="grey", ls="--", lw=0.8)
        ax.set(yscale="log", xlabel="injected motion error, RMS (px)", ylabel="MSE before / after",
               title="flow-error sensitivity (accurate solver, true motion + error)")
        written.append(_save(fig, out_dir / "flow_error.png"))
    return written


def _plain_log(axis) -> None:
    """A log axis labelled 1, 2, 5, 10, ... in plain numbers (the default crowds 3x10^0-style minor labels)."""
    from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

    axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FormatStrFormatter("%g"))
    axis.set_minor_formatter(NullFormatter())


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path
