"""The report of an estimate: typed, and written as ``report.json`` by :meth:`Report.to_json`.

Every stage that says something about an estimate (the summary line, ``--json``, the batch
summary, the preview, ``evaluate``, the bench) reads these fields. Relative figures are in percent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from . import __version__
from .files import FileStamp
from .solve.result import AccurateStats, PaperStats, stats_from_json

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
class PlaneCheck:
    """The hold-out check of one grid (:mod:`solve.holdout`): residual ratio, its standard error,
    whether it is below 1 by enough standard errors for the plane's correction to be kept, and the
    16 px blocks left out because the check's own fit disagreed there with the written map, and the
    side (px of the grid) of the central square checked (cut to the grid where it is smaller)."""

    residual_ratio: float
    standard_error: float
    passed: bool
    left_out_blocks: int = 0
    region_px: int | None = None


@dataclass(frozen=True)
class Holdout:
    """The check on the frame held out of the fit (:mod:`solve.holdout`): the brightness-constancy
    residual with k over without, over all planes, and its standard error; each grid's check in
    ``planes`` (a grid that fails is written as k = 1); ``passed`` when any plane's correction is kept."""

    frame: str
    residual_ratio: float
    passed: bool
    standard_error: float | None = None
    planes: dict = field(default_factory=dict)  # grid name -> PlaneCheck

    def to_json(self) -> dict:
        return {**vars(self), "planes": {name: vars(c).copy() for name, c in self.planes.items()}}

    @classmethod
    def from_json(cls, data: dict) -> "Holdout":
        planes = {name: PlaneCheck(**c) for name, c in (data.get("planes") or {}).items()}
        return cls(data["frame"], data["residual_ratio"], data["passed"], data.get("standard_error"), planes)


@dataclass(frozen=True)
class FrameMotion:
    """One frame's motion fit: corners tracked from the reference and the inliers kept, the
    residual under the chosen model on them (None where none was kept), the frame's RMS
    displacement from the reference, and ``H_t_ref`` in frame pixels (row-major 3x3)."""

    frame: str
    tracked: int
    inliers: int
    rms_px: float | None
    displacement_px: float
    homography: list


@dataclass(frozen=True)
class Layer:
    """A scene layer besides the dominant one: its motion model and the points that follow it."""

    model: str
    points: int


@dataclass(frozen=True)
class Motion:
    """The burst's motion: the chosen model and why, each frame's fit, the scene layers besides
    the dominant one, and the percentage of each frame's pixels left out as moving."""

    model: str
    reason: str = ""
    layers: tuple[Layer, ...] = ()
    frames: tuple[FrameMotion, ...] = ()
    refine_rounds: int = 0
    moving_percent: list | None = None

    def to_json(self) -> dict:
        return {**vars(self), "layers": [vars(x).copy() for x in self.layers],
                "frames": [vars(f).copy() for f in self.frames]}

    @classmethod
    def from_json(cls, data: dict) -> "Motion":
        return cls(**{**data, "layers": tuple(Layer(**x) for x in data["layers"]),
                      "frames": tuple(FrameMotion(**f) for f in data["frames"])})


@dataclass(frozen=True)
class Exposure:
    """Each frame's exposure relative to the reference's, reference first: ``fixed`` (taken as
    equal: no figures) or ``per-frame``, where ``relative`` is what was divided out (1 where the
    measured one did not differ significantly), with the ``measured`` values and the standard
    error of their logarithm (None where unmeasurable)."""

    mode: str = "fixed"
    relative: tuple[float, ...] | None = None
    measured: tuple[float, ...] | None = None
    log_standard_error: tuple[float | None, ...] | None = None

    @property
    def spread_percent(self) -> float:
        """The largest exposure difference (%) from the reference that was divided out; 0 if none."""
        return 100.0 * max(abs(c - 1.0) for c in self.relative or [1.0])

    def to_json(self) -> dict:
        if self.mode == "fixed":
            return {"mode": self.mode}
        return {"mode": self.mode, "relative": list(self.relative), "measured": list(self.measured),
                "log_standard_error": list(self.log_standard_error)}

    @classmethod
    def from_json(cls, data: dict) -> "Exposure":
        return cls(data["mode"], *(None if data.get(key) is None else tuple(data[key])
                                   for key in ("relative", "measured", "log_standard_error")))


@dataclass(frozen=True)
class SolverChoice:
    """The solver method used and why (``solver.method: auto`` chooses it from the burst's measured
    aliasing: the pairwise prediction error's excess over the noise, ``aliasing``; None where not
    measured). ``tried``: the methods run before the hold-out frame chose (their residual ratios
    in ``reason``); empty where one method was run."""

    method: str
    reason: str = ""
    aliasing: float | None = None
    tried: tuple = ()

    def to_json(self) -> dict:
        return vars(self).copy()

    @classmethod
    def from_json(cls, data: dict) -> "SolverChoice":
        return cls(**{**data, "tried": tuple(data.get("tried", ()))})


@dataclass(frozen=True)
class PlaneReport:
    """How one plane (a CFA colour, or Y) was solved: the solver (``paper`` / ``accurate``), the
    grid it was solved on (a CFA's two greens together for the accurate solver), the solver's
    counts, and for the accurate solver the FPN model chosen, every model's AIC, the input
    FPN split into EMVA 1288's parts (percent), whether the confidence was calibrated on two
    halves of the frames (:func:`solve.halves.calibrate`) and how far the column gains of the
    plane's top and bottom agree (standard errors; the column models are candidates from
    :data:`solve.fpnmodel.COLUMN_Z` on; None where that gate is not applied: k's error not measured
    on halves, or too few columns)."""

    method: str
    solved_on: str
    solver: PaperStats | AccurateStats
    fpn_model: str | None = None
    fpn_model_aic: dict | None = None
    input_fpn_percent: dict | None = None
    confidence_calibrated: bool = False
    column_agreement: float | None = None
    floor_dn: float | None = None  # photosites whose mean reading is at or below this were not solved
    too_dark_percent: float | None = None  # ... this share of the plane's
    fpn_base: str | None = None  # the structured model under the chosen one (solve.fpnmodel.FPNModel.base)

    def to_json(self) -> dict:
        """Flat, as ``report.json`` holds it: the method, the solver's counts, then the rest."""
        data = {"method": self.method, **vars(self.solver), "solved_on": self.solved_on}
        if self.fpn_model is not None:
            data.update(fpn_model=self.fpn_model, fpn_base=self.fpn_base, fpn_model_aic=self.fpn_model_aic,
                        input_fpn_percent=self.input_fpn_percent, confidence_calibrated=self.confidence_calibrated,
                        column_agreement=self.column_agreement)
        if self.floor_dn is not None:
            data.update(floor_dn=self.floor_dn, too_dark_percent=self.too_dark_percent)
        return data

    @classmethod
    def from_json(cls, data: dict) -> "PlaneReport":
        return cls(data["method"], data["solved_on"], stats_from_json(data["method"], data),
                   data.get("fpn_model"), data.get("fpn_model_aic"), data.get("input_fpn_percent"),
                   data.get("confidence_calibrated", False), data.get("column_agreement"), data.get("floor_dn"),
                   data.get("too_dark_percent"), data.get("fpn_base"))


@dataclass(frozen=True)
class Defects:
    """Defective photosites found (:mod:`defective`), by kind; ``dark_frame``: hot ones were also
    looked for in the dark frame."""

    hot: int = 0
    dead: int = 0
    stuck: int = 0
    dark_frame: bool = False

    @property
    def total(self) -> int:
        return self.hot + self.dead + self.stuck

    def to_json(self) -> dict:
        return {"total": self.total, "hot": self.hot, "dead": self.dead, "stuck": self.stuck,
                "dark_frame": self.dark_frame}

    @classmethod
    def from_json(cls, data: dict) -> "Defects":
        return cls(data["hot"], data["dead"], data["stuck"], data["dark_frame"])


@dataclass(frozen=True)
class Report:
    """What an estimate found and how: the report of :func:`pipeline.estimate`."""

    motion: Motion
    solver: SolverChoice | None = None  # None in reports written before the choice was reported
    prnu_percent: Prnu = field(default_factory=Prnu)
    predicted_residual_percent: float | None = None  # median predicted sigma_k (the accurate solver's)
    holdout: Holdout | None = None
    estimated_percent: float = 0.0
    inputs: tuple = ()  # FileStamp of every frame, in order
    dark: FileStamp | None = None
    white_level_dn: float | None = None
    reference: str = ""
    exposure: Exposure = field(default_factory=Exposure)
    defects: Defects | None = None  # None: not looked for (input.defects: false)
    planes: dict = field(default_factory=dict)  # plane name -> PlaneReport
    config: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)  # seconds per stage
    versions: dict = field(default_factory=dict)
    warnings: tuple = ()
    version: str = __version__

    @property
    def status(self) -> str:
        """``accepted`` (the held-out frame confirms the map, or some of its planes: the others
        were written as k = 1), ``rejected`` (it confirms none: k = 1 was written) or
        ``unchecked`` (no frame held out)."""
        if self.holdout is None:
            return "unchecked"
        return "accepted" if self.holdout.passed else "rejected"

    @property
    def fpn_models(self) -> str:
        """The FPN models chosen over the planes (the solver's method where it has none)."""
        return "/".join(sorted({p.fpn_model or p.method for p in self.planes.values()}))

    @property
    def exposure_spread_percent(self) -> float:
        """The largest exposure difference (%) from the reference that was divided out; 0 if none."""
        return self.exposure.spread_percent

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
            "holdout": None if self.holdout is None else self.holdout.to_json(),
            "estimated_percent": self.estimated_percent,
            "inputs": [s.to_json() for s in self.inputs],
            "dark": None if self.dark is None else self.dark.to_json(),
            "white_level_dn": self.white_level_dn,
            "reference": self.reference,
            "solver": None if self.solver is None else self.solver.to_json(),
            "motion": self.motion.to_json(),
            "exposure": self.exposure.to_json(),
            "defects": None if self.defects is None else self.defects.to_json(),
            "planes": {name: p.to_json() for name, p in self.planes.items()},
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
            motion=Motion.from_json(data["motion"]),
            solver=None if data.get("solver") is None else SolverChoice.from_json(data["solver"]),
            prnu_percent=Prnu.from_json(data["prnu_percent"]),
            predicted_residual_percent=data["predicted_residual_percent"],
            holdout=None if holdout is None else Holdout.from_json(holdout),
            estimated_percent=data["estimated_percent"],
            inputs=tuple(FileStamp(**i) for i in data["inputs"]),
            dark=None if data["dark"] is None else FileStamp(**data["dark"]),
            white_level_dn=data["white_level_dn"],
            reference=data["reference"],
            exposure=Exposure.from_json(data["exposure"]),
            defects=None if data.get("defects") is None else Defects.from_json(data["defects"]),
            planes={name: PlaneReport.from_json(p) for name, p in data["planes"].items()},
            config=data["config"],
            timings=data["timings"],
            versions=data["versions"],
            warnings=tuple(data["warnings"]),
            version=data["version"],
        )
