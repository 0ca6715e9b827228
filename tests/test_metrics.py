import json

import numpy as np
import pytest
from click.testing import CliRunner

from gainfpn_cli.cli import main
from gainfpn_cli import metrics
from gainfpn_cli.metrics import confidence_deciles, gain_bound, mixture_spread, robust_spread

READ, DN_PER_E = 3.0, 0.2


def _readings(rng, gain, electrons, n):
    """n readings per trial of a pixel of this gain: shot and read noise, rounded to DN, in electrons."""
    counts = rng.poisson(gain * electrons, (n,) + np.shape(gain)) + rng.normal(0.0, READ, (n,) + np.shape(gain))
    return np.round(counts * DN_PER_E) / DN_PER_E


@pytest.mark.parametrize("electrons", [30.0, 400.0, 6000.0])
def test_the_gain_bound_is_what_an_efficient_estimator_reaches(electrons):
    # with the scene known, the mean of a pixel's readings over the expected
    # signal is unbiased and efficient: its spread over trials is the bound
    rng = np.random.default_rng(1)
    estimates = _readings(rng, np.ones(40000), electrons, 8).mean(axis=0) / electrons
    bound = gain_bound(np.array(electrons), n_frames=8, read_noise_e=READ, dn_per_e=DN_PER_E)
    assert estimates.std() == pytest.approx(float(bound), rel=0.02)


def test_with_a_prior_the_bound_is_the_posterior_spread():
    # pixel gains drawn from the prior; the posterior mean's error spread is the Bayesian bound
    rng = np.random.default_rng(2)
    electrons, prior, n = 400.0, 0.01, 4
    gain = 1.0 + prior * rng.standard_normal(40000)
    direct = _readings(rng, gain, electrons, n).mean(axis=0) / electrons
    information = 1.0 / float(gain_bound(np.array(electrons), n_frames=n, read_noise_e=READ, dn_per_e=DN_PER_E)) ** 2
    posterior = (information * direct + 1.0 / prior**2) / (information + 1.0 / prior**2)
    bound = float(gain_bound(np.array(electrons), n_frames=n, read_noise_e=READ, dn_per_e=DN_PER_E, prior=prior))
    assert (posterior - gain).std() == pytest.approx(bound, rel=0.02)
    assert bound < 1.0 / np.sqrt(information) and bound < prior
    assert float(gain_bound(np.array(electrons), n_frames=n, read_noise_e=READ, dn_per_e=DN_PER_E, prior=0.0)) == 0


def test_mixture_spread_is_the_robust_spread_errors_of_those_sigmas_show():
    rng = np.random.default_rng(3)
    sigmas = np.repeat([0.002, 0.005, 0.02], [300000, 200000, 100000])
    expected = mixture_spread(sigmas)
    assert robust_spread(1.0 + sigmas * rng.standard_normal(sigmas.size)) == pytest.approx(expected, rel=0.01)
    assert mixture_spread(np.full(10, 0.01)) == pytest.approx(0.01, rel=1e-5)


def test_confidence_deciles_are_one_when_sigma_is_the_error_spread_and_scale_with_it():
    rng = np.random.default_rng(4)
    sigma = rng.uniform(0.001, 0.03, (300, 400))
    gain = rng.uniform(0.9, 1.1, sigma.shape)
    k = 1.7 / gain * (1.0 + sigma * rng.standard_normal(sigma.shape))  # any gauge: k's mean is not fixed
    mask = np.ones(sigma.shape, bool)
    mask[:, :5] = False
    honest = confidence_deciles(k, gain, sigma, mask)
    assert len(honest) == 10 and all(r == pytest.approx(1.0, abs=0.03) for r in honest), honest
    # a confidence twice too high reads 2 in every tenth; errors that do not grow with sigma show as a slope
    assert confidence_deciles(k, gain, sigma / 2, mask) == pytest.approx([2 * r for r in honest], rel=1e-9)
    flat = confidence_deciles(1.0 / gain * (1.0 + 0.01 * rng.standard_normal(sigma.shape)), gain, sigma, mask)
    assert flat[0] > 3 > 1 > flat[-1]
    assert confidence_deciles(k, gain, sigma, np.zeros(sigma.shape, bool)) == []


def _evaluated(tmp_path, *simulate):
    """A burst simulated with the ``simulate`` options, estimated (one worker) and evaluated by the CLI:
    its folder, the estimate's and the evaluation's CLI result."""
    runner = CliRunner()
    sim, out = tmp_path / "sim", tmp_path / "out"
    assert runner.invoke(main, ["simulate", str(sim), *simulate]).exit_code == 0
    assert runner.invoke(main, ["estimate", str(sim), "-o", str(out), "--quiet", "--workers", "1"]).exit_code == 0
    result = runner.invoke(main, ["evaluate", str(out), "--truth", str(sim)])
    assert result.exit_code == 0, result.output
    return sim, out, result


def test_evaluate_scores_a_map_written_k_1_as_no_correction(tmp_path):
    # a RAW burst of 5 frames is written k = 1 (checking.short_mosaic): what its frames get is scored,
    # where evaluate refused it before ("the gain map has no estimated pixel")
    sim, out, result = _evaluated(tmp_path, "--preset", "raw12", "--size", "160x128", "--frames", "5", "--seed", "2")
    scores = json.loads((out / "evaluation.json").read_text())
    assert scores["estimated_percent"] == 0 and scores["confidence_deciles"] == []
    assert scores["residual_fpn_percent"] == scores["input_fpn_percent"] > 0.5
    assert scores["mse_after"] == scores["mse_before"] and "MSE reduction 1.0x" in result.output


def test_evaluate_reports_the_bound_and_the_estimate_does_not_pass_it(tmp_path):
    # a 12-bit RGGB burst (sample_data's): 1 % pixel FPN, 8 frames, one held out to check
    sim, out, result = _evaluated(tmp_path, "--preset", "raw12", "--size", "160x128", "--frames", "8", "--seed", "2")
    assert "Cramer-Rao bound" in result.output
    scores = json.loads((out / "evaluation.json").read_text())
    assert scores["bound_frames"] == 7
    assert 0.3 < scores["residual_bound_percent"] < 1.0  # 1 % FPN, shot noise of ~6000 e-: about 0.5 %
    assert scores["residual_fpn_percent"] > scores["residual_bound_percent"]
    # the confidence's calibration, printed and recorded: 10 tenths of the written sigma_k
    assert len(scores["confidence_deciles"]) == 10 and all(r > 0 for r in scores["confidence_deciles"])
    assert "confidence: k's actual error over the sigma_k it states" in result.output
    # and each colour plane's residual, printed and recorded
    assert set(scores["plane_residual_fpn_percent"]) == {"R@00", "G@01", "G@10", "B@11"}
    assert "gain FPN after, by CFA plane (%): R@00 " in result.output
    # the whole frame's MSE reduction, printed where it differs from the estimated pixels' (here
    # measured 1.06x against 1.15x: the check kept planes covering 46 % of the photosites)
    frame = scores["frame_mse_before"] / scores["frame_mse_after"]
    ratio = scores["mse_before"] / scores["mse_after"]
    line = f"over the whole frame (k = 1 where not estimated): MSE reduction {frame:.1f}x"
    assert (line in result.output) == (f"{frame:.1f}" != f"{ratio:.1f}"), (frame, ratio)


def test_evaluate_scores_the_healthy_photosites_and_counts_the_defects_apart(tmp_path):
    # a burst with 2 % defects: the gain figures and the confidence's tenths are those of the photosites
    # the map estimated that the truth calls healthy; each kind of defect is counted, found or given a gain
    from gainfpn_cli.files import read_exr_planes
    from gainfpn_cli.sim.truth import load_truth
    from gainfpn_cli.solve.defects import KINDS
    from gainfpn_cli.solve.result import sigma_from_confidence

    sim, out, result = _evaluated(tmp_path, "--size", "128x96", "--frames", "6", "--seed", "4", "--defects", "0.02")
    scores = json.loads((out / "evaluation.json").read_text())
    truth = load_truth(sim)
    planes, _ = read_exr_planes(out / "gain_map.exr")
    k, confidence, written = planes["Y"], planes["confidence"], planes["defect"]
    est = confidence > 0
    healthy = est & (truth.defects == 0)
    assert scores["residual_fpn_percent"] == pytest.approx(metrics.residual_fpn_percent(k, truth.gain, healthy))
    assert scores["confidence_deciles"] == pytest.approx(
        confidence_deciles(k, truth.gain, sigma_from_confidence(confidence), healthy))
    assert scores["estimated_percent"] == pytest.approx(100.0 * est.mean())
    for kind, code in KINDS.items():
        mine = truth.defects == code
        assert scores["defects"][kind] == {"true": int(mine.sum()), "flagged": int((mine & (written != 0)).sum()),
                                           "given_a_gain": int((mine & est).sum())}
    assert scores["defects"]["healthy_flagged"] == int(((truth.defects == 0) & (written != 0)).sum())
    assert sum(scores["defects"][kind]["true"] for kind in KINDS) == int((truth.defects != 0).sum()) > 100
    assert "defective in the truth: hot " in result.output


def test_scores_over_the_whole_frame_count_what_the_map_did_not_estimate():
    # a map that estimates the left half only: its own figures are the left half's, the frame's take
    # the right half as written (k = 1) and leave out the photosites the truth calls defective
    from gainfpn_cli.sim.evaluate import scores
    from gainfpn_cli.sim.truth import Truth

    rng = np.random.default_rng(3)
    gain = 1.0 + 0.02 * rng.standard_normal((40, 60))
    ideal = rng.uniform(100.0, 200.0, gain.shape)
    frame0 = gain * ideal
    defects = np.zeros(gain.shape, np.uint8)
    defects[5, 50] = 1
    frame0[5, 50] = 4000.0  # a hot photosite on the right
    est = np.zeros(gain.shape, bool)
    est[:, :30] = True
    k = np.where(est, 1.0 / gain, 1.0)
    s = scores(k, est, frame0, Truth(gain, ideal, np.eye(3)[None], {}, defects))
    assert s["estimated_percent"] == 50.0 and s["mse_after"] == pytest.approx(0.0, abs=1e-20)
    healthy = defects == 0
    before = np.mean((frame0 - ideal)[healthy] ** 2)
    right = healthy & ~est
    assert s["frame_mse_before"] == pytest.approx(before, rel=1e-12)
    assert s["frame_mse_after"] == pytest.approx(np.sum((frame0 - ideal)[right] ** 2) / healthy.sum(), rel=1e-12)
    no_defects = scores(k, est, frame0, Truth(gain, ideal, np.eye(3)[None], {}))
    assert no_defects["frame_mse_before"] > 10 * s["frame_mse_before"]  # the hot photosite counted


def test_each_cfa_plane_is_scored_over_its_own_photosites():
    # k exact on the red photosites, 1 on the others, none estimated on blue: red's residual is 0, the
    # greens' their own input FPN, blue's not measured; a map without a CFA has no planes
    from gainfpn_cli.sim.evaluate import plane_residuals

    rng = np.random.default_rng(5)
    gain = 1.0 + 0.01 * rng.standard_normal((40, 60))
    k = np.ones(gain.shape)
    k[0::2, 0::2] = 1.0 / gain[0::2, 0::2]
    est = np.ones(gain.shape, bool)
    est[1::2, 1::2] = False
    planes = plane_residuals(k, est, gain, "RGGB")
    assert planes["R@00"] == pytest.approx(0.0, abs=1e-9)
    assert planes["G@01"] == pytest.approx(metrics.residual_fpn_percent(np.ones((20, 30)), gain[0::2, 1::2]))
    assert planes["G@10"] == pytest.approx(metrics.residual_fpn_percent(np.ones((20, 30)), gain[1::2, 0::2]))
    assert planes["B@11"] is None
    assert plane_residuals(k, est, gain, None) == {}
