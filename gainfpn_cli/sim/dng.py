"""DNG frames of simulated bursts (pidng): uncompressed CFA mosaics that rawpy reads back exactly."""

from __future__ import annotations

import os
from typing import Sequence

import numpy as np

from ..errors import InputError
from ..files import atomic_output


def write_dng(
    path: str | os.PathLike,
    mosaic: np.ndarray,
    *,
    bits: int,
    cfa: str,
    black: Sequence[int],
    white: int,
) -> None:
    """Write an uncompressed CFA DNG (pidng) that rawpy reads back exactly.

    Parameters
    ----------
    mosaic : ndarray of uint16, shape (H, W)
        Raw counts, black level included.
    bits : {8, 10, 12, 16}
        Stored bit depth (14-bit data go in a 16-bit container: pidng's 14-bit
        packing is wrong).
    cfa : str
        2x2 layout, e.g. ``"RGGB"``.
    black : sequence of 4 int
        Black level per 2x2 position, row-major.
    """
    try:
        from pidng.core import RAW2DNG, DNGTags, Tag
        from pidng.defs import CalibrationIlluminant, DNGVersion, PhotometricInterpretation
    except ImportError:
        raise InputError("writing DNG needs pidng: pip install 'gainfpn[dng]'") from None
    mosaic = np.asarray(mosaic)
    height, width = mosaic.shape
    if bits not in (8, 10, 12, 16):
        raise ValueError(f"bits must be 8, 10, 12 or 16, got {bits}")
    if (bits == 10 and width % 4) or (bits == 12 and width % 2):
        raise ValueError(f"{bits}-bit DNG needs a width divisible by {4 if bits == 10 else 2}, got {width}")
    if mosaic.dtype != np.uint16 or int(mosaic.max(initial=0)) >= 2**bits:
        raise ValueError(f"mosaic must be uint16 below 2**{bits}")
    codes = {"R": 0, "G": 1, "B": 2}
    tags = DNGTags()
    tags.set(Tag.ImageWidth, width)
    tags.set(Tag.ImageLength, height)
    tags.set(Tag.TileWidth, width)
    tags.set(Tag.TileLength, height)
    tags.set(Tag.Orientation, 1)
    tags.set(Tag.PhotometricInterpretation, PhotometricInterpretation.Color_Filter_Array)
    tags.set(Tag.SamplesPerPixel, 1)
    tags.set(Tag.BitsPerSample, bits)
    tags.set(Tag.CFARepeatPatternDim, [2, 2])
    tags.set(Tag.CFAPattern, [codes[c] for c in cfa])
    tags.set(Tag.BlackLevelRepeatDim, [2, 2])
    tags.set(Tag.BlackLevel, [int(b) for b in black])
    tags.set(Tag.WhiteLevel, int(white))
    tags.set(Tag.ColorMatrix1, [[1, 1], [0, 1], [0, 1], [0, 1], [1, 1], [0, 1], [0, 1], [0, 1], [1, 1]])
    tags.set(Tag.AsShotNeutral, [[1, 1], [1, 1], [1, 1]])
    tags.set(Tag.CalibrationIlluminant1, CalibrationIlluminant.D65)
    tags.set(Tag.DNGVersion, DNGVersion.V1_4)
    tags.set(Tag.DNGBackwardVersion, DNGVersion.V1_2)
    tags.set(Tag.Make, "gainfpn")
    tags.set(Tag.Model, "simulator")
    writer = RAW2DNG()
    writer.options(tags, path="", compress=False)
    data = bytes(writer.convert(mosaic))
    with atomic_output(path) as tmp:
        tmp.write_bytes(data)
