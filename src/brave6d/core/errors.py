"""User-facing error types.

Every error a user can cause (bad spec, bad file, unsolvable geometry) is a
:class:`BraveError`; the CLI prints it as one line naming the file, field or
frame, never as a traceback.  Programming errors stay ordinary exceptions.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any


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


#: Location parts of a pydantic error that name a union member or a validator, not a field.
_NOT_FIELD_PREFIXES = ("function-", "constrained-")
_UNION_TAGS = frozenset({"str", "int", "float", "bool", "none", "list", "dict"})


def validation_error_field(errors: Sequence[Mapping[str, Any]], *, dotted: bool = False,
                           skip: int = 0) -> tuple[str, str]:
    """``(field, message)`` of the first of pydantic's ``ValidationError.errors()``, the one way
    every file reader and the server name a bad field.

    ``field`` is ``episodes[3].ar`` (``dotted``: ``estimates.0.R``, the server's wire style) with
    union tags and validator names left out, ``""`` for the root; ``skip`` drops leading parts
    (a tagged union's tag). ``message`` is pydantic's without its ``Value error, `` prefix, plus
    ``(and N more)`` when there are more errors.
    """
    if not errors:
        return "", "invalid"
    err = errors[0]
    parts = [p for p in tuple(err.get("loc", ()))[skip:]
             if not (isinstance(p, str) and ("[" in p or p in _UNION_TAGS or p.startswith(_NOT_FIELD_PREFIXES)))]
    field = ""
    for part in parts:
        if dotted:
            field += ("." if field else "") + str(part)
        else:
            field += f"[{part}]" if isinstance(part, int) else ("." if field else "") + str(part)
    message = str(err.get("msg", "invalid")).removeprefix("Value error, ")
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    return field, message + more
