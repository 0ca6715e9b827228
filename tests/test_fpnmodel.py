import numpy as np
import pytest

from gainfpn_cli import metrics
from gainfpn_cli.accurate import solve_accurate
from gainfpn_cli.fpnmodel import MODELS, select_model, structured_parts
from gainfpn_cli.simulate import PRESETS, simulate_burst, with_overrides

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
    k, confidence, _ = _k_map(np.random.default_rng(1), **fpn)
    assert select_model(k, confidence).chosen == expected


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
    # pixel part also holds the 0.5 % estimation noise: sqrt(3^2 + 0.5^2) = 3.04 %;
    # 120 columns give the column sigma to ~1/sqrt(2*120) = 6 %
    assert split["pixel"] == pytest.approx(3.04, rel=0.05)
    assert split["column"] == pytest.approx(4.0, rel=0.2)
    assert split["row"] == pytest.approx(1.0, rel=0.05)


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
    mask = (result.confidence > 0) & metrics.interior_mask(frames.shape[1:], 8)
    assert metrics.residual_fpn_percent(model.k, burst.gain, mask) < metrics.residual_fpn_percent(
        result.k, burst.gain, mask)
