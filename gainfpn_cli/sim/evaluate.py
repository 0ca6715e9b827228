"""Score an estimate against the truth of the simulation it was made from."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import ATTR_CFA, find_frames, read_exr_planes, read_frame, stamp
from ..geometry.planes import plane_views
from ..metrics import confidence_deciles, mse, residual_fpn_percent
from ..outputs import read_gain_map
from ..report import Report
from ..solve.defects import KINDS
from ..solve.result import sigma_from_confidence
from .truth import load_truth, residual_bound_percent


def evaluate(out_dir: Path, sim_dir: Path) -> dict:
    """Residual gain FPN, the paper's MSE before/after and the confidence's calibration (per tenth of
    the written sigma_k, k's actual error over it: ``metrics.confidence_deciles``), against a
    simulation's truth: over the photosites the map estimated that the truth calls healthy. Where
    the simulation has defects, also how many of each kind the map found (:func:`defect_counts`).

    Refuses a truth that is not this estimate's: another size, CFA layout or white level
    (bit depth), or frames whose digests differ from those the estimate recorded."""

    k, attrs = read_gain_map(out_dir / "gain_map.exr")
    planes, _ = read_exr_planes(out_dir / "gain_map.exr")
    confidence = planes.get("confidence", np.ones(k.shape[:2], np.float32))
    report = _read_report(out_dir)
    truth = load_truth(sim_dir)
    sim_paths = find_frames([sim_dir])
    first = read_frame(sim_paths[0])
    _check_truth(report, attrs, k, truth, first, sim_paths, out_dir, sim_dir)
    est = confidence > 0
    # a defective photosite's error is not a gain's (a hot one's offset, a dead or stuck one's reading):
    # the gain figures are the healthy photosites', the defects counted apart
    healthy = np.ones(est.shape, bool) if truth.defects is None else truth.defects == 0
    scored = est & healthy
    written = bool(scored.any())  # else k = 1 everywhere (the check turned every plane away): scored as
    if not written:  # the frames get it, no correction, and the confidence states nothing to score
        scored = healthy
    result = {**scores(k[..., 0], scored, first.data[..., 0], truth), "estimated_percent": 100.0 * float(est.mean())}
    n_fit = len(report.inputs) - (1 if report.holdout else 0)  # one frame is held out to check k
    bound = residual_bound_percent(truth, scored, n_fit)
    deciles = confidence_deciles(k[..., 0], truth.gain, sigma_from_confidence(confidence), scored) if written else []
    result.update(residual_bound_percent=bound, bound_frames=n_fit, confidence_deciles=deciles,
                  plane_residual_fpn_percent=plane_residuals(k[..., 0], scored, truth.gain, attrs.get(ATTR_CFA)))
    if truth.defects is not None:
        result["defects"] = defect_counts(truth.defects, planes.get("defect"), est)
    return result


def defect_counts(truth: np.ndarray, written: np.ndarray | None, est: np.ndarray) -> dict:
    """Per kind of defect in the ``truth`` (codes of :data:`solve.defects.KINDS`): how many photosites,
    how many of them the map's ``written`` defect channel codes defective (any kind), and how many it
    gave a gain (``est``: confidence above 0); and how many healthy photosites it codes defective."""
    flagged = np.zeros(truth.shape, bool) if written is None else written != 0
    counts = {kind: {"true": int(np.count_nonzero(truth == code)),
                     "flagged": int(np.count_nonzero((truth == code) & flagged)),
                     "given_a_gain": int(np.count_nonzero((truth == code) & est))}
              for kind, code in KINDS.items()}
    return {**counts, "healthy_flagged": int(np.count_nonzero((truth == 0) & flagged))}


def plane_residuals(k: np.ndarray, est: np.ndarray, gain: np.ndarray, cfa: str | None) -> dict:
    """The residual gain FPN (percent) of each colour plane of a CFA mosaic over its estimated
    photosites, by plane name (``R@00``, ...; empty without a CFA, None for a plane with none)."""
    if not cfa:
        return {}
    out = {}
    for name, pick, _ in plane_views(cfa, ("Y",)):
        inside = pick(est[..., None])
        out[name] = residual_fpn_percent(pick(k[..., None]), pick(gain[..., None]), inside) if inside.any() else None
    return out


def _read_report(out_dir: Path) -> Report:
    path = out_dir / "report.json"
    try:
        report = Report.from_json(json.loads(path.read_text(encoding="utf-8")))
        report.inputs[0].sha256
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc}); is {out_dir} a folder written by "
                         "`gainfpn estimate`?") from None
    except (ValueError, KeyError, TypeError, IndexError):
        raise InputError(f"{path}: not a report of this gainfpn version (no input digests); estimate again") from None
    return report


def _check_truth(report, attrs, k, truth, first, sim_paths, out_dir: Path, sim_dir: Path) -> None:
    """Raise :class:`InputError` unless ``sim_dir`` holds the burst the estimate in ``out_dir`` was made from."""
    h, w = truth.gain.shape
    if (h, w) != k.shape[:2]:
        raise InputError(f"{sim_dir}: truth is {w}x{h}, the gain map {k.shape[1]}x{k.shape[0]}: not this estimate's "
                         "simulation")
    sim_cfa, est_cfa = first.info.cfa or "none", attrs.get(ATTR_CFA) or "none"
    if sim_cfa != est_cfa:
        raise InputError(f"{sim_dir}: CFA layout {sim_cfa} differs from the estimate's ({est_cfa}): not this "
                         "estimate's simulation")
    sim_white, est_white = first.info.layout()[4], report.white_level_dn
    if sim_white != est_white:
        raise InputError(f"{sim_dir}: white level {_dn(sim_white)} differs from the estimate's frames' "
                         f"({_dn(est_white)}): another bit depth, not this estimate's simulation")
    recorded = {Path(i.path).name: i.sha256 for i in report.inputs}
    for path in sim_paths:
        if path.name in recorded and stamp(path).sha256 != recorded.pop(path.name):
            raise InputError(f"{path}: differs from the frame {path.name} the estimate in {out_dir} was made from "
                             "(another simulation, or frames made again)")
    if recorded:
        raise InputError(f"{sim_dir}: has no frame {sorted(recorded)[0]}, which the estimate in {out_dir} was made "
                         "from: not this estimate's simulation")


def _dn(value) -> str:
    return "not stated" if value is None else f"{value:g} DN"


def scores(k: np.ndarray, est: np.ndarray, frame0: np.ndarray, truth) -> dict:
    """Residual gain FPN and the paper's MSE of frame 0 before/after ``k``, over the pixels ``est``,
    and the MSE over the whole frame (``frame_mse_*``: every photosite the truth calls healthy, with
    the map as written, k = 1 where it estimated nothing): what a user's frame gets, comparable
    between maps that estimate different pixels (a plane the hold-out check keeps or turns away)."""
    healthy = np.ones(k.shape, bool) if truth.defects is None else truth.defects == 0
    return {
        "estimated_percent": 100.0 * float(est.mean()),
        "input_fpn_percent": residual_fpn_percent(np.ones_like(k), truth.gain, est),
        "residual_fpn_percent": residual_fpn_percent(k, truth.gain, est),
        "mse_before": mse(frame0, truth.ideal, est),
        "mse_after": mse(k * frame0, truth.ideal, est),
        "mse_floor": mse(frame0 / truth.gain, truth.ideal, est),
        "frame_mse_before": mse(frame0, truth.ideal, healthy),
        "frame_mse_after": mse(k * frame0, truth.ideal, healthy),
    }
