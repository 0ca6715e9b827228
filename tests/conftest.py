"""Shared fixtures: everything is generated, seeded, and small."""

from __future__ import annotations

import numpy as np
import pytest

from gainfpn_cli.simulate import PRESETS, Shake, simulate_burst


@pytest.fixture(scope="session")
def paper_burst():
    """The paper's sensor, 8 frames of 96x128, hand-held shake."""
    return simulate_burst(shape=(96, 128), n_frames=8, sensor=PRESETS["paper"], shake=Shake(), seed=11)


@pytest.fixture()
def rng():
    return np.random.default_rng(1234)
