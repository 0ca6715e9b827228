"""Exceptions a user can meet; the CLI turns each into one line and exit 1."""

#: Exit status of ``estimate`` / ``batch`` with ``--strict`` when the hold-out frame rejects an estimate
#: (k = 1 was written). 1 is a user error, 2 a usage error, 130 / 143 an interrupt.
EXIT_REJECTED = 3


class GainFPNError(Exception):
    """Base class of every error gainfpn reports to the user."""


class ConfigError(GainFPNError):
    """A configuration file, preset or flag is wrong."""


class InputError(GainFPNError):
    """An input file or directory is missing, unreadable or inconsistent."""


class EstimationError(GainFPNError):
    """The data do not allow an estimate (no motion, no texture, ...)."""


class TrackingError(EstimationError):
    """A frame's motion could not be fitted: too few points tracked into it."""
