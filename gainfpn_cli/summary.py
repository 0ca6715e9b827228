"""What a run says: the one-line summaries and the ``--json`` records, from an estimate's report.

Plain functions of the report dict ``pipeline.estimate`` builds (and ``report.json`` holds),
so ``estimate``, ``batch`` and a script reading ``report.json`` say the same thing.
"""

from __future__ import annotations

from pathlib import Path

#: Exit status of ``estimate`` / ``batch`` with ``--strict`` when the hold-out frame rejects an estimate
#: (k = 1 was written). 1 is a user error, 2 a usage error, 130 / 143 an interrupt.
EXIT_REJECTED = 3


def _pct(value: float | None, digits: int = 2) -> str:
    return "not measured" if value is None else f"{value:.{digits}f} %"


def prnu_text(prnu: dict) -> str:
    """``PRNU 5.02 % (pixel 4.98, column 0.41, row 0.12 %)``, or what is missing."""
    if prnu.get("total") is None:
        return "PRNU not measured (the paper method has no FPN model)"
    return (f"PRNU {prnu['total']:.2f} % (pixel {prnu['pixel']:.2f}, column {prnu['column']:.2f}, "
            f"row {prnu['row']:.2f} %)")


def holdout_text(holdout: dict | None) -> str:
    if holdout is None:
        return "hold-out off"
    verdict = "accepted" if holdout["passed"] else "rejected: k = 1 written"
    return f"hold-out {verdict} (residual ratio {holdout['residual_ratio']:.3f})"


def exposure_spread_percent(report: dict) -> float:
    """The largest exposure difference (%) from the reference that an estimate's report says was
    divided out; 0 when none was."""
    return 100.0 * max(abs(c - 1.0) for c in report.get("exposure", {}).get("relative", [1.0]))


def fpn_models(report: dict) -> str:
    return "/".join(sorted({p.get("fpn_model", p["method"]) for p in report["planes"].values()}))


def estimate_line(report: dict, out_dir: Path) -> str:
    """The line ``estimate`` prints: what the lab measures first, then how it was obtained."""
    spread = exposure_spread_percent(report)
    after = report["predicted_residual_percent"]
    return (f"{prnu_text(report['prnu_percent'])}"
            + (f" -> predicted residual {after:.2f} %" if after is not None else "")
            + f"; {holdout_text(report['holdout'])}; {len(report['inputs'])} frames, motion "
            f"{report['motion']['model']}, FPN model {fpn_models(report)}, {report['estimated_percent']:.0f} % "
            "of pixels estimated"
            + (f", exposures differ by up to {spread:.1f} % (divided out)" if spread > 0 else "")
            + f" -> {out_dir}")


def estimate_record(report: dict, out_dir: Path, *, untouched: tuple = ()) -> dict:
    """The ``--json`` record of an estimate."""
    corrected = out_dir / "corrected"
    return {
        "status": report["status"],
        "prnu_percent": report["prnu_percent"],
        "predicted_residual_percent": report["predicted_residual_percent"],
        "holdout": report["holdout"],
        "estimated_percent": report["estimated_percent"],
        "motion_model": report["motion"]["model"],
        "fpn_models": fpn_models(report),
        "warnings": report["warnings"],
        "outputs": {"folder": str(out_dir.absolute()),
                    "gain_map": str((out_dir / "gain_map.exr").absolute()),
                    "corrected": str(corrected.absolute()) if corrected.is_dir() else None,
                    "report": str((out_dir / "report.json").absolute())},
        "untouched": list(untouched),
    }
