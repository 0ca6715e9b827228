"""Shared fixtures: everything is generated, seeded, and small."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import settings

from gainfpn_cli.sim.motion import Shake
from gainfpn_cli.sim.sensor import PRESETS
from gainfpn_cli.sim.simulate import simulate_burst

# The same examples on every run (the suite is deterministic); a search for
# new failures: HYPOTHESIS_PROFILE=explore python -m pytest tests/test_fuzz.py
settings.register_profile("deterministic", derandomize=True, database=None)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "deterministic"))


@pytest.fixture(scope="session")
def paper_burst():
    """The paper's sensor, 8 frames of 96x128, hand-held shake."""
    return simulate_burst(shape=(96, 128), n_frames=8, sensor=PRESETS["paper"], shake=Shake(), seed=11)


@pytest.fixture()
def rng():
    return np.random.default_rng(1234)


@pytest.fixture(scope="module")
def small_sim(tmp_path_factory):
    """``gainfpn simulate`` of a small burst (helpers.SMALL); read-only: copy it to change it."""
    from helpers import SMALL, run_cli

    folder = tmp_path_factory.mktemp("small") / "burst"
    run_cli("simulate", folder, *SMALL)
    return folder


@pytest.fixture(scope="module")
def small_estimate(small_sim, tmp_path_factory):
    """``gainfpn estimate`` of :func:`small_sim`; read-only: copy it to change it."""
    from helpers import run_cli

    folder = tmp_path_factory.mktemp("small") / "est"
    run_cli("estimate", small_sim, "-o", folder, "-q", "--workers", "1")
    return folder
