"""The simulated sensor: its noise, ADC and gain pattern (docs/method.md sections 1 and 4)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

CFA_CHANNEL = {"R": 0, "G": 1, "B": 2}


@dataclass(frozen=True)
class Sensor:
    """Sensor and ADC; defaults are the paper's sensor (docs/method.md section 4)."""

    conversion_gain_uv: float = 32.5  # uV per electron
    swing_v: float = 1.0  # output swing, V
    read_noise_e: float = 50.0  # electrons RMS
    adc_bits: int = 8
    black_level: int = 0  # DN added before the ADC clips
    fpn_pixel: float = 0.05  # sigma of the per-pixel gain
    fpn_column: float = 0.0  # sigma of the per-column gain
    fpn_row: float = 0.0  # sigma of the even/odd-row gain
    cfa: str | None = None  # 2x2 layout such as "RGGB", or None (monochrome)
    shot_noise: bool = True  # Poisson photon noise (off only for tests of the model)

    @property
    def full_well_e(self) -> float:
        return self.swing_v / (self.conversion_gain_uv * 1e-6)

    @property
    def white_level(self) -> int:
        return 2**self.adc_bits - 1

    @property
    def dn_per_e(self) -> float:
        return self.white_level / self.full_well_e


#: Named sensors: the paper's, and a 12-bit RGGB camera for DNG bursts.
PRESETS = {
    "paper": Sensor(),
    "raw12": Sensor(conversion_gain_uv=50.0, swing_v=1.0, read_noise_e=3.0, adc_bits=12, black_level=256,
                    fpn_pixel=0.01, cfa="RGGB"),
}


def with_overrides(sensor: Sensor, **changes) -> Sensor:
    """``sensor`` with the given fields replaced (None values are ignored)."""
    return dataclasses.replace(sensor, **{k: v for k, v in changes.items() if v is not None})


def gain_pattern(shape: tuple[int, int], sensor: Sensor, rng: np.random.Generator) -> np.ndarray:
    """True gain ``a`` = (1 + pixel) * (1 + column) * (1 + even/odd row), float32."""
    h, w = shape
    pixel = 1.0 + sensor.fpn_pixel * rng.standard_normal(shape)
    column = 1.0 + sensor.fpn_column * rng.standard_normal(w)
    row_pair = 1.0 + sensor.fpn_row * rng.standard_normal(2)
    row = row_pair[np.arange(h) % 2]
    return np.clip(pixel * column[None, :] * row[:, None], 0.05, None).astype(np.float32)
