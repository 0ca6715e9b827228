"""The report of an estimate: typed, and written as ``report.json`` by :meth:`Report.to_json`.

Every stage that says something about an estimate (the summary line, ``--json``, the batch
summary, the preview, ``evaluate``, the bench) reads these fields. Three are still plain data
whose keys depend on the solver or the model: ``planes``, ``exposure`` and ``motion.frames``.
Relative figures are in percent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from . import __version__
from .files import FileStamp

#: The parts of the gain nonuniformity EMVA 1288 separates.
PRNU_PARTS = ("pixel", "column", "row")


@dataclass(frozen=True)
class Prnu:
    """The input gain nonuniformity in EMVA 1288's parts (percent of the mean gain): ``pixel``,
    ``column`` and ``row`` (even/odd rows), and their quadrature sum ``total``; per plane in
    ``planes`` and, at the top, combined over the planes (root mean square). None where the
    solver has no FPN model to split it (the paper method)."""

    total: float | None = None
    pixel: float | None = None
    column: float | None = None
    row: float | None = None
    planes: dict = field(default_factory=dict)  # plane name -> Prnu

    @classmethod
    def of(cls, parts: dict) -> "Prnu":
        """From the FPN model's split of one plane (``{"pixel": .., "column": .., "row": ..}``)."""
        values = {part: float(parts[part]) for part in PRNU_PARTS}
        return cls(total=math.sqrt(sum(v**2 for v in values.values())), **values)

    @classmethod
    def combined(cls, planes: dict) -> "Prnu":
        """Every plane's split (plane name -> parts) and their combination; empty: not measured."""
        if not planes:
            return cls()
        per_plane = {name: cls.of(parts) for name, parts in planes.items()}
        rms = {part: math.sqrt(sum(getattr(p, part) ** 2 for p in per_plane.values()) / len(per_plane))
               for part in PRNU_PARTS}
        return replace(cls.of(rms), planes=per_plane)

    def to_json(self, *, nested: bool = True) -> dict:
        """The four figures, and with ``nested`` every plane's under ``planes``."""
        parts = {"total": self.total, "pixel": self.pixel, "column": self.column, "row": self.row}
        if nested:
            parts["planes"] = {name: p.to_json(nested=False) for name, p in self.planes.items()}
        return parts

    @classmethod
    def from_json(cls, data: dict) -> "Prnu":
        planes = {name: cls.from_json(p) for name, p in (data.get("planes") or {}).items()}
        return cls(data["total"], data["pixel"], data["column"], data["row"], planes)


@dataclass(frozen=True)
class Holdout:
    """The check on the frame held out of the fit: the brightness-constancy residual with k over
    without; ``passed`` when k reduces it."""

    frame: str
    residual_ratio: float
    passed: bool


@dataclass(frozen=True)
class Motion:
    """The burst's motion: the chosen model and why, each frame's fit (``frames``: name, point
    counts, residual, displacement and ``H_t_ref`` in frame pixels), the scene layers besides the
    dominant one, and the percentage of each frame's pixels left out as moving."""

    model: str
    reason: str = ""
    layers: list = field(default_factory=list)
    frames: list = field(default_factory=list)
    refine_rounds: int = 0
    moving_percent: list | None = None


@dataclass(frozen=True)
class Report:
    """What an estimate found and how: the report of :func:`pipeline.estimate`."""

    status: str  # accepted / rejected (k = 1 written) / unchecked: what the held-out frame said
    motion: Motion
    prnu_percent: Prnu = field(default_factory=Prnu)
    predicted_residual_percent: float | None = None  # median predicted sigma_k (the accurate solver's)
    holdout: Holdout | None = None
    estimated_percent: float = 0.0
    inputs: tuple = ()  # FileStamp of every frame, in order
    dark: FileStamp | None = None
    white_level_dn: float | None = None
    reference: str = ""
    # per frame, reference first: its exposure relative to the reference's ("relative", divided out)
    exposure: dict = field(default_factory=dict)
    planes: dict = field(default_factory=dict)  # plane name -> the solver's and the FPN model's figures
    config: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)  # seconds per stage
    versions: dict = field(default_factory=dict)
    warnings: tuple = ()
    version: str = __version__

    @property
    def fpn_models(self) -> str:
        """The FPN models chosen over the planes (the solver's method where it has none)."""
        return "/".join(sorted({p.get("fpn_model", p["method"]) for p in self.planes.values()}))

    @property
    def exposure_spread_percent(self) -> float:
        """The largest exposure difference (%) from the reference that was divided out; 0 if none."""
        return 100.0 * max(abs(c - 1.0) for c in self.exposure.get("relative", [1.0]))

    def with_timings(self, **seconds: float) -> "Report":
        """This report with more stages' times, and ``total_s`` their sum."""
        timings = {**{k: v for k, v in self.timings.items() if k != "total_s"}, **seconds}
        return replace(self, timings={**timings, "total_s": sum(timings.values())})

    def to_json(self) -> dict:
        """``report.json``: what a lab measures first, then how it was obtained."""
        return {
            "version": self.version,
            "status": self.status,
            "prnu_percent": self.prnu_percent.to_json(),
            "predicted_residual_percent": self.predicted_residual_percent,
            "holdout": None if self.holdout is None else vars(self.holdout).copy(),
            "estimated_percent": self.estimated_percent,
            "inputs": [s.to_json() for s in self.inputs],
            "dark": None if self.dark is None else self.dark.to_json(),
            "white_level_dn": self.white_level_dn,
            "reference": self.reference,
            "motion": vars(self.motion).copy(),
            "exposure": self.exposure,
            "planes": self.planes,
            "config": self.config,
            "timings": self.timings,
            "versions": self.versions,
            "warnings": list(self.warnings),
        }

    @classmethod
    def from_json(cls, data: dict) -> "Report":
        """The report ``to_json`` wrote; KeyError or TypeError if it is not one."""
        holdout = data["holdout"]
        return cls(
            status=data["status"],
            motion=Motion(**data["motion"]),
            prnu_percent=Prnu.from_json(data["prnu_percent"]),
            predicted_residual_percent=data["predicted_residual_percent"],
            holdout=None if holdout is None else Holdout(**holdout),
            estimated_percent=data["estimated_percent"],
            inputs=tuple(FileStamp(**i) for i in data["inputs"]),
            dark=None if data["dark"] is None else FileStamp(**data["dark"]),
            white_level_dn=data["white_level_dn"],
            reference=data["reference"],
            exposure=data["exposure"],
            planes=data["planes"],
            config=data["config"],
            timings=data["timings"],
            versions=data["versions"],
            warnings=tuple(data["warnings"]),
            version=data["version"],
        )


def status_of(holdout: Holdout | None) -> str:
    """``accepted`` (the hold-out frame confirms the map), ``rejected`` (it did not: k = 1 was
    written) or ``unchecked`` (no frame held out)."""
    if holdout is None:
        return "unchecked"
    return "accepted" if holdout.passed else "rejected"
