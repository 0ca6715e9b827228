"""gainfpn: gain fixed-pattern-noise correction from a moving burst.

Implements S. Lim and A. El Gamal, *Gain Fixed Pattern Noise Correction via
Optical Flow* (docs/method.md). From Python::

    import gainfpn_cli as gainfpn

    result = gainfpn.estimate("captures/", preset="balanced")   # -> gainfpn.Estimate
    result.write("calib/")

:func:`estimate`, :func:`apply` and :class:`Estimate` are :mod:`gainfpn_cli.api`'s, loaded on
first use so that ``gainfpn --help`` stays fast.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("gainfpn")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0+unknown"

__all__ = ["Estimate", "apply", "estimate", "__version__"]


def __getattr__(name: str):
    if name in ("Estimate", "apply", "estimate"):
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'gainfpn_cli' has no attribute {name!r}")
