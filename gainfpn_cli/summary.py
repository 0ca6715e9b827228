"""What a run says: the one-line summary and the ``--json`` record of an estimate, from its
:class:`report.Report`, so ``estimate``, ``batch`` and the preview say the same thing."""

from __future__ import annotations

from pathlib import Path

from .report import Holdout, Prnu, Report


def prnu_text(prnu: Prnu, report: Report | None = None) -> str:
    """``PRNU 5.02 % (pixel 4.98, column 0.41, row 0.12 %)``, or what is missing (and why, from ``report``:
    the paper method has no FPN model; a CFA mosaic too short to measure it is in the warnings)."""
    if prnu.total is None:
        paper = report is None or any(p.method == "paper" for p in report.planes.values())
        return "PRNU not measured" + (" (the paper method has no FPN model)" if paper else " (see the warnings)")
    return f"PRNU {prnu.total:.2f} % (pixel {prnu.pixel:.2f}, column {prnu.column:.2f}, row {prnu.row:.2f} %)"


def holdout_text(holdout: Holdout | None) -> str:
    if holdout is None:
        return "hold-out off"
    failed = [name for name, check in holdout.planes.items() if not check.passed]
    if not holdout.passed:
        verdict = "rejected: k = 1 written"
    else:
        verdict = "accepted" + (f" ({', '.join(failed)}: k = 1 written)" if failed else "")
    error = "" if holdout.standard_error is None else f" +- {holdout.standard_error:.3f}"
    return f"hold-out {verdict} (residual ratio {holdout.residual_ratio:.3f}{error})"


def after_text(report: Report) -> str:
    after = report.predicted_residual_percent
    return "" if after is None else f" -> predicted residual {after:.2f} %"


def defects_text(defects) -> str:
    """``, 12 defective photosites (10 hot, 1 dead, 1 stuck)``, or nothing when none were found."""
    if defects is None or defects.total == 0:
        return ""
    kinds = ", ".join(f"{n} {kind}" for kind, n in (("hot", defects.hot), ("dead", defects.dead),
                                                     ("stuck", defects.stuck)) if n)
    return f", {defects.total} defective photosites ({kinds})"


def estimate_line(report: Report, out_dir: Path) -> str:
    """The line ``estimate`` prints: what the lab measures first, then how it was obtained."""
    spread = report.exposure_spread_percent
    return (f"{prnu_text(report.prnu_percent, report)}{after_text(report)}; {holdout_text(report.holdout)}; "
            f"{len(report.inputs)} frames, motion {report.motion.model}, FPN model {report.fpn_models}, "
            f"{report.estimated_percent:.0f} % of pixels estimated"
            + (f", exposures differ by up to {spread:.1f} % (divided out)" if spread > 0 else "")
            + defects_text(report.defects)
            + f" -> {out_dir}")


def estimate_record(report: Report, out_dir: Path, *, untouched: tuple = ()) -> dict:
    """The ``--json`` record of an estimate."""
    full = report.to_json()
    corrected = out_dir / "corrected"
    return {
        **{key: full[key] for key in ("status", "prnu_percent", "predicted_residual_percent", "holdout",
                                      "estimated_percent", "defects")},
        "motion_model": report.motion.model,
        "fpn_models": report.fpn_models,
        "warnings": list(report.warnings),
        "outputs": {"folder": str(out_dir.absolute()),
                    "gain_map": str((out_dir / "gain_map.exr").absolute()),
                    "corrected": str(corrected.absolute()) if corrected.is_dir() else None,
                    "report": str((out_dir / "report.json").absolute())},
        "untouched": list(untouched),
    }
