import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gainfpn_cli import metrics
from gainfpn_cli.geometry.resample import masked_window_mean, window_sum
from gainfpn_cli.sim.sensor import PRESETS, with_overrides
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.solve import fpnmodel
from gainfpn_cli.solve.accurate import solve_accurate
from gainfpn_cli.solve.fpnmodel import (
    MODELS,
    pixel_prior_variance,
    select_model,
    structured_parts,
)
from gainfpn_cli.solve.halves import Calibration, Halves, calibrate, departure
from gainfpn_cli.solve.result import sigma_from_confidence

SIGMA = 0.005  # standard error of every synthetic k


def _k_map(rng, *, pixel=0.0, column=0.0, row=0.0, shape=(80, 120)):
    """k = 1 / a for a = pixel x column x even/odd row gains, plus estimation noise of SIGMA."""
    h, w = shape
    a = (1 + pixel * rng.standard_normal(shape)) * (1 + column * rng.standard_normal(w))[None, :]
    a = a * np.array([1 + row, 1 - row])[np.arange(h) % 2][:, None]
    k = 1 / a * (1 + SIGMA * rng.standard_normal(shape))
    confidence = np.full(shape, 1 / (1 + (SIGMA / 0.01) ** 2))
    return k, confidence, a


def test_structured_parts_are_exact_without_noise():
    h, w = 20, 30
    col = np.linspace(0.9, 1.1, w)
    row = np.array([1.02, 0.98])
    k = col[None, :] * row[np.arange(h) % 2][:, None]
    got_col, got_row = structured_parts(k, np.ones((h, w)), rounds=5)
    np.testing.assert_allclose(got_col * got_row.mean(), col / col.mean() * row.mean(), rtol=1e-9)
    np.testing.assert_allclose(got_row[0] / got_row[1], row[0] / row[1], rtol=1e-9)


@pytest.mark.parametrize(
    "fpn, expected",
    [
        (dict(column=0.03), "column"),
        (dict(row=0.02), "row"),
        (dict(column=0.03, row=0.02), "column+row"),
        (dict(pixel=0.03), "pixel"),
        (dict(pixel=0.02, column=0.03), "pixel"),
    ],
)
def test_aic_picks_the_model_that_made_the_data(fpn, expected):
    # a model with one parameter more than the truth wins by chance with
    # P(chi2_1 > 2) = 16 %: column data may come out column+row (the row
    # part then within the noise; counted in the next test)
    k, confidence, _ = _k_map(np.random.default_rng(1), **fpn)
    model = select_model(k, confidence)
    assert model.chosen == expected or (expected, model.chosen) == ("column", "column+row")
    # the structured model the map is built on: the chosen one, or the one the pixel model shrinks toward,
    # which holds the column FPN where there is one (and, by AIC, whatever else fits the pixel FPN best)
    assert model.base == model.chosen if model.chosen != "pixel" else model.base in set(MODELS) - {"pixel"}
    assert "column" in model.base or "column" not in fpn


def test_aic_chooses_the_truth_as_often_as_it_should():
    # 40 maps each: column+row data must always be column+row (its fit was not
    # at k's level and lost to the pixel model 7 times in 40); column data is
    # column but for AIC's 16 % chance of the one-parameter-larger model
    # (measured 33 of 40)
    def chosen(seed, **fpn):
        return select_model(*_k_map(np.random.default_rng(seed), **fpn)[:2]).chosen

    assert all(chosen(seed, column=0.03, row=0.02) == "column+row" for seed in range(40))
    picks = [chosen(seed, column=0.03) for seed in range(40)]
    assert set(picks) <= {"column", "column+row"} and picks.count("column") >= 28


def test_no_fpn_gets_no_visible_pattern():
    # AIC takes the 1-parameter row model by chance with P(chi2_1 > 2) = 16 %;
    # either way the map must not add a pattern: its spread stays far below
    # the 0.5 % noise of the individual k
    k, confidence, _ = _k_map(np.random.default_rng(1))
    model = select_model(k, confidence)
    assert model.chosen in ("none", "row")
    assert metrics.robust_spread(model.k) < 0.0005


def test_split_reports_the_input_fpn():
    k, confidence, _ = _k_map(np.random.default_rng(2), pixel=0.03, column=0.04, row=0.01)
    split = select_model(k, confidence).split
    # the pixel part is the prior's s: the 0.5 % estimation noise is taken out
    # (sqrt(3^2 + 0.5^2) = 3.04 % with it); 120 columns give the column sigma
    # to ~1/sqrt(2*120) = 6 %
    assert split["pixel"] == pytest.approx(3.0, rel=0.02)
    assert split["column"] == pytest.approx(4.0, rel=0.2)
    assert split["row"] == pytest.approx(1.0, rel=0.05)


def test_uncertain_pixels_are_shrunk_toward_the_structured_model():
    # 1 % pixel FPN, k's standard error from 0.1 % to 8 % across the frame
    rng = np.random.default_rng(6)
    shape = (100, 120)
    a = 1 + 0.01 * rng.standard_normal(shape)
    sigma = np.exp(rng.uniform(np.log(0.001), np.log(0.08), shape))
    k = 1 / a + sigma * rng.standard_normal(shape)
    confidence = 1 / (1 + (sigma / 0.01) ** 2)
    model = select_model(k, confidence)
    assert model.chosen == "pixel"
    assert model.split["pixel"] == pytest.approx(1.0, rel=0.05)
    rms = lambda k_: 100 * np.sqrt(np.mean((k_ * a / np.mean(k_ * a) - 1) ** 2))  # noqa: E731
    err_raw, err = rms(k), rms(model.k)
    # the posterior mean's RMS error: sqrt(mean(s^2 sigma^2 / (s^2 + sigma^2))) with s = 1 %
    expected = 100 * np.sqrt(np.mean(1e-4 * sigma**2 / (1e-4 + sigma**2)))
    assert err < 0.3 * err_raw
    assert err == pytest.approx(expected, rel=0.1)
    sure = sigma < 0.0015  # well-measured pixels keep their own k (w >= 0.98)
    np.testing.assert_allclose(model.k[sure] / model.k[sure].mean(), k[sure] / k[sure].mean(), atol=1e-3)


def test_prior_variance_is_zero_when_deviations_are_only_noise():
    rng = np.random.default_rng(7)
    sigma = np.full(5000, 0.01)
    assert pixel_prior_variance(sigma * rng.standard_normal(5000) * 0.98, sigma) == 0.0
    assert pixel_prior_variance(np.array([]), np.array([])) == 0.0


def test_structured_model_beats_per_pixel_k_on_structured_fpn():
    k, confidence, a = _k_map(np.random.default_rng(3), column=0.04)
    model = select_model(k, confidence)
    assert metrics.residual_fpn_percent(model.k, a) < 0.2 * metrics.residual_fpn_percent(k, a)


def test_force_and_validation():
    k, confidence, _ = _k_map(np.random.default_rng(4), column=0.03)
    for name in MODELS:
        assert select_model(k, confidence, force=name).chosen == name
    with pytest.raises(ValueError, match="force must be one of"):
        select_model(k, confidence, force="fancy")


def test_unestimated_pixels():
    k, confidence, _ = _k_map(np.random.default_rng(5), pixel=0.03)
    confidence[:10] = 0.0
    model = select_model(k, confidence)
    assert model.chosen == "pixel" and np.all(model.k[:10] == 1.0)
    assert model.k[10:].mean() == pytest.approx(1.0, abs=1e-6)


def test_end_to_end_column_sensor_gets_a_column_model():
    sensor = with_overrides(PRESETS["paper"], fpn_pixel=0.0, fpn_column=0.04)
    burst = simulate_burst(shape=(96, 128), n_frames=8, seed=1, sensor=sensor)
    frames = burst.frames.astype(np.float32)
    result = solve_accurate(frames, burst.homographies, saturation=burst.saturation, workers=1)
    model = select_model(result.k, result.confidence)
    assert model.chosen in ("column", "column+row")
    weight = np.where(result.confidence > 0, 1 / np.maximum(sigma_from_confidence(result.confidence), 1e-6) ** 2, 0)
    assert fpnmodel.column_agreement(result.k, weight.astype(np.float32)) > fpnmodel.COLUMN_Z  # measured 17
    mask = (result.confidence > 0) & metrics.interior_mask(frames.shape[1:], 8)
    assert metrics.residual_fpn_percent(model.k, burst.gain, mask) < metrics.residual_fpn_percent(
        result.k, burst.gain, mask)


def test_an_error_along_part_of_a_column_is_not_taken_for_column_fpn(monkeypatch):
    # each column's k errs by 1 % in its top half and independently in its bottom half (a vertical
    # edge's interpolation error): AIC alone fits it with a column model, which the pixel model then
    # builds on; a sensor's column FPN runs down the whole column (the column tests above). The gate
    # applies where k's error is measured: here a calibration given (factor 1, the true pixel FPN)
    shipped = fpnmodel.COLUMN_Z
    measured = Calibration(np.zeros(1), np.ones(1), 0.01**2)

    def case(seed, gate):
        rng = np.random.default_rng(seed)
        k, confidence, a = _k_map(rng, pixel=0.01)
        k[:40] *= 1 + 0.01 * rng.standard_normal(k.shape[1])
        k[40:] *= 1 + 0.01 * rng.standard_normal(k.shape[1])
        monkeypatch.setattr(fpnmodel, "COLUMN_Z", shipped if gate else -np.inf)
        model = select_model(k, confidence, calibration=measured)
        assert abs(model.column_agreement) < 2.0
        return 100 * np.std(model.k * a / np.mean(model.k * a))

    for seed in range(6):  # measured 0.91-1.07 % with the gate, 0.95-1.11 % by AIC alone
        assert case(seed, gate=True) < case(seed, gate=False) - 0.015
    k, confidence, _ = _k_map(np.random.default_rng(0), pixel=0.01)
    assert np.isnan(select_model(k, confidence).column_agreement)  # not measured: AIC alone


def _halves(rng, *, pixel=0.02, factor=2.0, shape=(160, 200)):
    """A full fit and two halves of a pixel-FPN map whose k errors are ``factor`` times the
    predicted sigma_k (which varies 4x over the map); the full fit's error is the halves' mean."""
    sigma = np.geomspace(0.002, 0.008, shape[1])[None, :] * np.ones(shape)
    truth = 1 + pixel * rng.standard_normal(shape)
    e_a, e_b = (factor * np.sqrt(2) * sigma * rng.standard_normal(shape) for _ in range(2))
    confidence = 1 / (1 + (sigma / 0.01) ** 2)
    ones = np.ones(shape)
    return truth, truth + (e_a + e_b) / 2, confidence, Halves(truth + e_a, ones, truth + e_b, ones)


def test_two_halves_measure_the_error_of_k_and_the_pixel_fpn():
    truth, k, confidence, halves = _halves(np.random.default_rng(3))
    sigma = sigma_from_confidence(confidence)
    calibration = calibrate(k, sigma, halves, np.ones(k.shape), confidence > 0)
    np.testing.assert_allclose(calibration.factor, 2.0, rtol=0.1)  # every decile's
    assert np.sqrt(calibration.prior) == pytest.approx(0.02, rel=0.03)
    # fewer pixels (a dark plane's, where many readings are near black): fewer parts of as many pixels
    def crop(n):
        maps = (halves.k_a, halves.confidence_a, halves.k_b, halves.confidence_b)
        return calibrate(k[:n, :n], sigma[:n, :n], Halves(*(m[:n, :n] for m in maps)), np.ones((n, n)),
                         confidence[:n, :n] > 0)

    few = crop(78)  # 6084 px: six parts
    assert len(few.factor) == 6
    np.testing.assert_allclose(few.factor, 2.0, rtol=0.15)  # 3 standard errors of a 1000 px part (PART_PIXELS)
    assert np.sqrt(few.prior) == pytest.approx(0.02, rel=0.05)
    assert crop(77) is None  # 5929 px: too few to measure


def test_a_half_that_tells_nothing_at_a_pixel_does_not_set_its_tenth():
    # a few photosites where one half has next to no estimate (its sigma_k 40x the full fit's; the
    # half's comparisons there were discounted) and the full fit strays below both halves (as six
    # pixels of a green plane of a 16-frame RGGB photograph burst did): their Hausman terms, each
    # -192 sigma_k^2, took the most precise tenth's factor to 0.62 where k errs as predicted
    truth, k, confidence, halves = _halves(np.random.default_rng(8), factor=1.0)
    sigma = sigma_from_confidence(confidence)
    rows, columns = slice(40, 43), slice(0, 4)  # 12 pixels in the tenth of the smallest sigma_k
    s = sigma[rows, columns]
    k_a, k_b, confidence_b = halves.k_a.copy(), halves.k_b.copy(), halves.confidence_b.copy()
    k[rows, columns] = truth[rows, columns] - 4 * s
    k_a[rows, columns] = truth[rows, columns] + 4 * s
    k_b[rows, columns] = truth[rows, columns] + 20 * s
    confidence_b[rows, columns] = 1 / (1 + (40 * s / 0.01) ** 2)
    halves = Halves(k_a, halves.confidence_a, k_b, confidence_b)
    calibration = calibrate(k, sigma, halves, np.ones(k.shape), confidence > 0)
    np.testing.assert_allclose(calibration.factor, 1.0, rtol=0.1)  # 0.62 in the first tenth with them


def test_a_spot_where_both_halves_failed_does_not_set_its_tenth():
    # a spot of 20 pixels where both halves' fits failed (k off by 60 % and 20 %, their sigma_k still
    # within HALF_SIGMA_RATIO) and the full fit by 4 %, as on a 9-frame RGGB burst of a photograph
    # with clipped highlights: their Hausman terms, each over 10^4 times the tenth's median, took
    # the tenth to the factor's floor (0.1) where its other 3180 pixels err as predicted
    truth, k, confidence, halves = _halves(np.random.default_rng(9), factor=1.0)
    sigma = sigma_from_confidence(confidence)
    clean = calibrate(k, sigma, halves, np.ones(k.shape), confidence > 0)
    rows, columns = slice(60, 64), slice(70, 75)  # in the fourth tenth of sigma_k
    k_a, k_b = halves.k_a.copy(), halves.k_b.copy()
    k[rows, columns] = truth[rows, columns] + 0.04
    k_a[rows, columns] = truth[rows, columns] + 0.6
    k_b[rows, columns] = truth[rows, columns] + 0.2
    calibration = calibrate(k, sigma, Halves(k_a, halves.confidence_a, k_b, halves.confidence_b),
                            np.ones(k.shape), confidence > 0)
    assert calibration.factor[3] >= 0.9 * clean.factor[3]  # the spot's own error the halves cannot tell
    np.testing.assert_allclose(np.delete(calibration.factor, 3), np.delete(clean.factor, 3), rtol=1e-6)


def test_the_pixel_model_shrinks_by_the_measured_error():
    # sigma_k 2x too small: Paule-Mandel takes the missed noise for pixel FPN; the halves do not,
    # the written sigma_k predicts the written k's error and the map is closer to the truth
    truth, k, confidence, halves = _halves(np.random.default_rng(4), pixel=0.01)
    plain, measured = select_model(k, confidence), select_model(k, confidence, halves=halves)
    assert plain.split["pixel"] > 1.2 and measured.split["pixel"] == pytest.approx(1.0, rel=0.05)
    assert plain.sigma is None and measured.chosen == "pixel"
    error = measured.k - truth
    assert np.sqrt(np.mean(error**2)) / np.sqrt(np.mean(measured.sigma**2)) == pytest.approx(1.0, abs=0.1)
    assert np.std(measured.k - truth) < np.std(plain.k - truth)


def test_the_none_model_writes_the_pixel_fpn_as_its_error():
    # k = 1 errs by the pixel FPN (0.3 %), not by the per-pixel fit's error (0.4-1.6 % here): written as
    # that, an 8-frame RGGB burst whose red, blue and one green took `none` read 0.13-1.09 in its tenths
    truth, k, confidence, halves = _halves(np.random.default_rng(5), pixel=0.003)
    model = select_model(k, confidence, halves=halves, force="none")
    assert np.all(model.k == 1) and model.split["pixel"] == pytest.approx(0.3, rel=0.1)
    error = model.k - truth
    assert np.sqrt(np.mean(error**2)) / np.sqrt(np.mean(model.sigma**2)) == pytest.approx(1.0, abs=0.1)


@pytest.mark.parametrize("pixel, along", [(0.0, 1), (0.002, 1), (0.0, 16)])
def test_a_column_model_writes_the_error_of_its_gains_and_the_pixel_fpn_it_leaves(pixel, along):
    # a column FPN of 1 %, k's error 0.4-1.6 % per pixel and the same over runs of ``along`` rows (a column
    # gain then averages fewer independent errors): the written sigma_k, the per-pixel fit's before (over
    # 10x too large), is the column gains' error and the pixel FPN together
    rng = np.random.default_rng(6)
    shape = (160, 200)
    sigma = np.geomspace(0.002, 0.008, shape[1])[None, :] * np.ones(shape)
    truth = (1 + 0.01 * rng.standard_normal(shape[1]))[None, :] * (1 + pixel * rng.standard_normal(shape))

    def error():
        e = 2 * np.sqrt(2) * sigma * rng.standard_normal(shape)
        return np.repeat(e[::along], along, axis=0)[: shape[0]] if along > 1 else e

    e_a, e_b = error(), error()
    ones = np.ones(shape)
    halves = Halves(truth + e_a, ones, truth + e_b, ones)
    model = select_model(truth + (e_a + e_b) / 2, 1 / (1 + (sigma / 0.01) ** 2), halves=halves, force="column")
    actual = model.k / model.k.mean() - truth / truth.mean()
    assert np.sqrt(np.mean(actual**2)) / np.sqrt(np.mean(model.sigma**2)) == pytest.approx(1.0, abs=0.15)


def test_an_error_the_full_fit_has_and_neither_half_does_is_counted():
    # a smooth 10 % dip in the full fit only (as comparisons of near frames left one at a frame edge of a
    # raw12 bench burst): the halves' Hausman difference reads it as less error, the departure from the
    # halves' mean as what it is, and the pixel model then shrinks it away
    truth, k, confidence, halves = _halves(np.random.default_rng(5), pixel=0.01, factor=1.0)
    y, x = np.mgrid[: k.shape[0], : k.shape[1]]
    dip = -0.1 * np.exp(-((y - 80) ** 2 + (x - 30) ** 2) / (2 * 5.0**2))
    strayed = departure(k + dip, halves, confidence > 0)
    assert np.mean(strayed[np.abs(dip) > 0.03] > 0) > 0.95
    assert np.mean(strayed[np.abs(dip) < 1e-4] > 0) < 1e-3
    assert np.sqrt(strayed[80, 30]) == pytest.approx(0.1, rel=0.2)
    model = select_model(k + dip, confidence, halves=halves)
    assert model.chosen == "pixel"
    inside = np.abs(dip) > 0.03
    assert np.sqrt(np.mean((model.k - truth)[inside] ** 2)) < 0.3 * np.sqrt(np.mean(dip[inside] ** 2))
    deciles = metrics.confidence_deciles(model.k, 1 / truth, model.sigma, confidence > 0)
    assert 0.75 <= min(deciles) and max(deciles) <= 1.25, deciles


def test_an_error_both_halves_share_is_counted_and_not_taken_for_pixel_fpn():
    # interpolating a sharp scene errs alike in every fit: both halves share that error, so their
    # Hausman difference misses it and their covariance takes it for pixel FPN. Here it is 3x sigma_k
    # on the sharper half of the map (where sigma_k is larger, as at a scene's edges)
    rng = np.random.default_rng(6)
    truth, k, confidence, halves = _halves(rng, pixel=0.01, factor=1.0)
    sigma = sigma_from_confidence(confidence)
    shared = np.where(sigma > np.median(sigma), 3.0 * sigma * rng.standard_normal(k.shape), 0.0)
    halves = Halves(halves.k_a + shared, halves.confidence_a, halves.k_b + shared, halves.confidence_b)
    calibration = calibrate(k + shared, sigma, halves, np.ones(k.shape), confidence > 0)
    assert np.sqrt(calibration.prior) == pytest.approx(0.01, rel=0.05)
    # k's error over sigma_k in each decile of sigma_k: 1 in the lower five, sqrt(1 + 3^2) above
    np.testing.assert_allclose(calibration.factor, [1.0] * 5 + [np.sqrt(10.0)] * 5, rtol=0.1)
    model = select_model(k + shared, confidence, halves=halves)
    deciles = metrics.confidence_deciles(model.k, 1 / truth, model.sigma, confidence > 0)
    assert 0.75 <= min(deciles) and max(deciles) <= 1.25, deciles
    assert np.std(model.k - truth) < 0.8 * np.std(truth)


def test_a_smooth_error_both_halves_share_where_the_fpn_hides_it_is_counted():
    # a colour plane's aliasing that the fit spreads over flat patches: both halves err alike, over a few
    # pixels, by as much as the noise, on the most precise fifth of the map. Against a 1 % pixel FPN it
    # does not stand out of the parts' scatter about the FPN (halves._shared's gate stays shut), but the
    # FPN, independent from one photosite to the next, has no covariance between the halves 2 px apart.
    # (12 seeds: the two tenths 1.26-1.57 and 1.11-1.48, the others at most 1.08; without the smooth
    # error every tenth 0.97-1.04)
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(8)
    truth, k, confidence, halves = _halves(rng, pixel=0.01, factor=1.0)
    sigma = sigma_from_confidence(confidence)
    smooth = gaussian_filter(rng.standard_normal(k.shape), 3.0)
    smooth *= np.where(sigma < np.quantile(sigma, 0.2), sigma, 0.0) / smooth.std()
    halves = Halves(halves.k_a + smooth, halves.confidence_a, halves.k_b + smooth, halves.confidence_b)
    calibration = calibrate(k + smooth, sigma, halves, np.ones(k.shape), confidence > 0)
    # k's error over sigma_k: sqrt(1 + 1) in the lowest two tenths (read 2 px away, at a correlation of
    # 0.85), 1 in the others
    np.testing.assert_allclose(calibration.factor[:2], np.sqrt(2.0), rtol=0.2)
    np.testing.assert_allclose(calibration.factor[3:], 1.0, rtol=0.1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_chance_high_of_the_fpn_where_sigma_is_least_is_not_taken_for_shared_error(seed):
    # 5 % pixel FPN, its spread 2 % wider in the most precise tenth (a part's FPN variance scatters by
    # about 3 % of itself on 3200 pixels: a chance high), and an error both halves share of 3x sigma_k in
    # the least precise tenth, which opens the shared error's gate. Read part by part, the high took the
    # most precise tenth's factor to 1.04-4.08 (seeds 0-5; k errs 1x there); the parts' excesses fitted
    # non-decreasing in sigma_k pool it with its neighbours': 0.97-1.01
    rng = np.random.default_rng(seed)
    truth, k, confidence, halves = _halves(rng, pixel=0.05, factor=1.0)
    sigma = sigma_from_confidence(confidence)
    add = np.zeros(k.shape)
    add[:, :20] = 0.02 * (truth[:, :20] - 1)  # sigma_k rises along the columns: the first 20 are the lowest tenth
    add += np.where(sigma > np.quantile(sigma, 0.9), 3.0 * sigma * rng.standard_normal(k.shape), 0.0)
    halves = Halves(halves.k_a + add, halves.confidence_a, halves.k_b + add, halves.confidence_b)
    calibration = calibrate(k + add, sigma, halves, np.ones(k.shape), confidence > 0)
    np.testing.assert_allclose(calibration.factor[:8], 1.0, atol=0.1)
    assert calibration.factor[-1] > 2.5  # sqrt(1 + 3^2), taken in as far as it stands out of its noise


@pytest.mark.parametrize("seed", [0, 1])
def test_a_mosaic_colour_plane_keeps_a_shared_error_where_sigma_is_least(seed):
    # aliasing on a colour plane errs most in flat patches, where sigma_k is least: an error both halves
    # share of 3x sigma_k on the most precise tenth. Halves of a mosaic's plane (monotone False) read it
    # part by part (sqrt(1 + 3^2)); fitted non-decreasing in sigma_k it is spread over the other tenths
    # (1.16-1.20, 1.01-1.14 above), which on a 12 MP x 16 12-bit RGGB burst left its lowest tenth at 1.40x
    rng = np.random.default_rng(seed)
    truth, k, confidence, halves = _halves(rng, pixel=0.01, factor=1.0)
    sigma = sigma_from_confidence(confidence)
    shared = np.where(sigma < np.quantile(sigma, 0.1), 3.0 * sigma * rng.standard_normal(k.shape), 0.0)
    factors = {}
    for monotone in (True, False):
        both = Halves(halves.k_a + shared, halves.confidence_a, halves.k_b + shared, halves.confidence_b, monotone)
        factors[monotone] = calibrate(k + shared, sigma, both, np.ones(k.shape), confidence > 0).factor
    assert factors[False][0] == pytest.approx(np.sqrt(10.0), rel=0.1)
    np.testing.assert_allclose(factors[False][1:], 1.0, atol=0.1)
    assert factors[True][0] < 1.5


def test_the_pixel_fpn_is_not_sliced_by_its_own_sigma():
    # a pixel's sigma_k falls with its own gain (its readings' information): on a flat scene the
    # deciles of its own sigma_k are deciles of the FPN itself, each far narrower than the whole
    rng = np.random.default_rng(7)
    shape = (160, 200)
    truth = 1 + 0.05 * rng.standard_normal(shape)
    sigma = 0.01 * truth * np.geomspace(1.0, 1.2, shape[1])[None, :]
    e_a, e_b = (np.sqrt(2) * sigma * rng.standard_normal(shape) for _ in range(2))
    ones = np.ones(shape)
    halves = Halves(truth + e_a, ones, truth + e_b, ones)
    calibration = calibrate(truth + (e_a + e_b) / 2, sigma, halves, ones, ones > 0)
    assert np.sqrt(calibration.prior) == pytest.approx(0.05, rel=0.03)
    np.testing.assert_allclose(calibration.factor, 1.0, rtol=0.1)


@pytest.mark.parametrize("seed", [0, 1])
def test_no_shared_error_is_read_where_the_deciles_of_sigma_mix_bright_and_dark_pixels(seed):
    # a scene of patches 10 % apart in level: sigma_k goes as 1 / (gain x level), so the middle decile of a
    # pixel's own sigma_k holds the low gains of the bright patches and the high gains of the dark ones,
    # and its deviations spread far wider than the pixel FPN. That is no error of k: read by such deciles
    # the shared error gave that decile a factor of 4.4-4.7 (three seeds), and on a smooth 8-bit burst
    # 1.5-3.4 in three deciles whose k erred 0.6x the written sigma_k. By the neighbours' sigma_k, with the
    # parts' chance scatter not taken for shared error (SHARED_P), every factor is 1
    rng = np.random.default_rng(seed)
    shape = (240, 320)
    truth = 1 + 0.05 * rng.standard_normal(shape)
    y, x = np.mgrid[: shape[0], : shape[1]]
    level = np.where((y // 40 + x // 40) % 2 == 0, 1.0, 0.9)
    sigma = 0.003 / (truth * level)
    e_a, e_b = (np.sqrt(2) * sigma * rng.standard_normal(shape) for _ in range(2))
    ones = np.ones(shape)
    calibration = calibrate(truth + (e_a + e_b) / 2, sigma, Halves(truth + e_a, ones, truth + e_b, ones), ones,
                            ones > 0)
    np.testing.assert_allclose(calibration.factor, 1.0, rtol=0.1)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_the_pixel_fpn_is_not_sliced_by_its_own_sigma_in_the_window_either(seed):
    # sigma_k set by a smooth scene (1.2x over the plane) and the pixel's own gain (as gain^-2): the
    # window's mean sigma_k^2 that orders the prior's parts must leave the pixel out, or the most
    # precise parts hold the highest gains and a narrower FPN (measured with it in: 2.4-3.7 % low)
    import cv2

    rng = np.random.default_rng(seed)
    shape = (240, 320)
    truth = 1 + 0.05 * rng.standard_normal(shape)
    field = cv2.GaussianBlur(rng.standard_normal(shape), (0, 0), 8)
    sigma = 0.004 * 1.2 ** ((field - field.min()) / np.ptp(field)) / truth**2
    e_a, e_b = (np.sqrt(2) * sigma * rng.standard_normal(shape) for _ in range(2))
    ones = np.ones(shape)
    calibration = calibrate(truth + (e_a + e_b) / 2, sigma, Halves(truth + e_a, ones, truth + e_b, ones), ones,
                            ones > 0)
    assert calibration.prior == pytest.approx(np.var(truth), rel=0.02)
    np.testing.assert_allclose(calibration.factor, 1.0, rtol=0.1)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), top=st.integers(0, 39), left=st.integers(0, 49),
       height=st.integers(1, 40), width=st.integers(1, 50), side=st.sampled_from([3, 5, 9]))
def test_the_masked_window_mean_over_the_mask_box_is_the_one_over_the_plane(seed, top, left, height, width, side):
    # the halves' region of a plane, anywhere (at its edges too), with holes: summing only around it
    # gives every pixel the mean the whole plane's window sums give, bit for bit
    rng = np.random.default_rng(seed)
    values = rng.random((40, 50), dtype=np.float32)
    mask = np.zeros(values.shape, bool)
    mask[top:top + height, left:left + width] = rng.random((40, 50))[top:top + height, left:left + width] > 0.2
    count = window_sum(mask.astype(np.float32), side)
    total = window_sum(np.where(mask, values, np.float32(0)), side)
    plane = np.divide(total, count, out=np.zeros_like(total), where=count > 0)
    np.testing.assert_array_equal(masked_window_mean(values, mask, side), plane)


def test_the_prior_standard_error_counts_errors_correlated_over_neighbours():
    # k's errors spread over neighbouring pixels (here a 3x3 box of white noise, as an interpolation
    # kernel spreads a reading's noise): the priors of 24 bursts scatter by what the stated standard
    # error says (measured 1.08x), where the formula for independent pixels gives half of it (1.97x)
    import cv2

    shape, priors, stated = (160, 200), [], []
    for seed in range(24):
        rng = np.random.default_rng(seed)
        truth = 1 + 0.01 * rng.standard_normal(shape)

        def error():
            return 3 * 0.04 * cv2.blur(rng.standard_normal(shape), (3, 3))  # 4 % RMS, noise-dominated

        e_a, e_b = error(), error()
        sigma = np.full(shape, 0.04 / np.sqrt(2))
        ones = np.ones(shape)
        c = calibrate(truth + (e_a + e_b) / 2, sigma, Halves(truth + e_a, ones, truth + e_b, ones), ones, ones > 0)
        priors.append(c.prior - np.var(truth))
        stated.append(c.prior_se)
    assert np.std(priors) / np.sqrt(np.mean(np.square(stated))) == pytest.approx(1.0, abs=0.35)


def _measured(prior, se):
    return Calibration(np.zeros(1), np.ones(1), prior, prior_se=se)


def test_planes_priors_are_pooled_where_they_agree_within_chance():
    planes = {"R@00": _measured(1.4e-4, 0.6e-4), "G@01": _measured(0.5e-4, 0.3e-4), "G@10": _measured(0.4e-4, 0.3e-4),
              "B@11": _measured(1.5e-4, 0.7e-4), "X": None}
    pooled = fpnmodel.pooled_priors(planes)
    assert pooled["X"] is None
    assert [c.prior for c in pooled.values() if c] == pytest.approx([0.95e-4] * 4)
    assert pooled["R@00"].prior_se == pytest.approx(np.sqrt(0.36 + 0.09 + 0.09 + 0.49) * 1e-4 / 4)
    assert all(c.shared == 0 for c in pooled.values() if c)
    # a plane whose prior is far above the others' (an error its halves share, aliasing): the lowest that
    # agree are pooled, taken from the lowest up, and its excess is counted as k's error, not as FPN
    apart = fpnmodel.pooled_priors({**planes, "B@11": _measured(4.0e-4, 0.2e-4)})
    assert [c.prior for c in apart.values() if c] == pytest.approx([(1.4e-4 + 0.5e-4 + 0.4e-4) / 3] * 4)
    assert [c.shared for c in apart.values() if c] == pytest.approx([0, 0, 0, 4.0e-4 - 2.3e-4 / 3])
    sigma = np.array([0.01, np.inf], np.float32)
    assert apart["B@11"].sigma(sigma)[0] == pytest.approx(np.sqrt(0.01**2 + 4.0e-4 - 2.3e-4 / 3), rel=1e-5)
    assert apart["B@11"].sigma(sigma)[1] == np.inf and apart["R@00"].sigma(sigma)[0] == pytest.approx(0.01)
    # the lowest one far below the rest: pooled alone, the others' excess counted
    low = fpnmodel.pooled_priors({**planes, "G@10": _measured(0.01e-4, 0.001e-4)})
    assert low["R@00"].prior == pytest.approx(0.01e-4) and low["R@00"].shared == pytest.approx(1.39e-4)
    # one plane, or priors that were not measured (the solver's own sigma_k): nothing to pool
    one = {"Y": planes["R@00"]}
    assert fpnmodel.pooled_priors(one) is one
    unmeasured = {n: Calibration(np.zeros(1), np.ones(1), 1e-4, measured=False) for n in ("R@00", "B@11")}
    assert fpnmodel.pooled_priors(unmeasured) is unmeasured
