"""Exceptions raised by the core.

Every failure that a caller can act on is a :class:`LocalizationError`; the
service maps each subclass to one problem+json response. Anything else that
escapes the core is a bug.
"""

from __future__ import annotations


class LocalizationError(Exception):
    """Base class for every expected failure of a localisation computation.

    Parameters
    ----------
    message : str
        Human-readable explanation, shown to API clients as ``detail``.
    loc : tuple of (str or int), optional
        Path of the offending input, when one input is to blame, in core names
        (``("measurements", 3, "sigma_azimuth_rad")``); the service maps it to the API's field path.
    """

    code = "localization_error"

    def __init__(self, message: str, loc: tuple[str | int, ...] | None = None):
        super().__init__(message)
        self.message = message
        self.loc = loc


class InvalidInput(LocalizationError):
    """A value is outside its domain (e.g. a non-positive sigma)."""

    code = "invalid_input"


class TooFewMeasurements(LocalizationError):
    """The method needs more measurements or lines of sight than were given."""

    code = "too_few_measurements"


class UnobservableGeometry(LocalizationError):
    """The geometry does not determine the position (rank-deficient information)."""

    code = "unobservable"


class AmbiguousGeometry(LocalizationError):
    """Two distinct points fit the measurements as well as each other and nothing physical tells them apart
    (the message names both; an ``initial_guess`` near one picks it)."""

    code = "ambiguous_geometry"


class NotConverged(LocalizationError):
    """An iteration failed to produce any usable estimate."""

    code = "not_converged"
