"""gainfpn: gain fixed-pattern-noise correction from a moving burst.

Implements S. Lim and A. El Gamal, *Gain Fixed Pattern Noise Correction via
Optical Flow*, with the conventions of the project's METHOD notes.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("gainfpn")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0+unknown"
