"""User-facing error types.

Every error a user can cause (bad spec, bad file, unsolvable geometry) is a
:class:`BraveError`; the CLI prints it as one line naming the file, field or
frame, never as a traceback.  Programming errors stay ordinary exceptions.
"""

from __future__ import annotations


class BraveError(Exception):
    """Base class for errors whose message is meant for the user (one line)."""


class SpecError(BraveError, ValueError):
    """A scene spec (YAML) is malformed; the message names the file and the field."""


class NonRigidTransformError(BraveError, ValueError):
    """A 4x4 matrix that should be a rigid transform is not (scaled, sheared, NaN, ...)."""


class DataError(BraveError, ValueError):
    """A data file (frame record, image, JSON) is missing or corrupt; the message names it."""


class DegenerateGeometryError(BraveError, ValueError):
    """A geometric problem cannot be solved as posed (e.g. too few or parallel rotation axes)."""
