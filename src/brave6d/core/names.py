"""Names that become parts of paths: one validator for all of them, and one for relative paths.

A dataset's ``name`` and ``version``, a scene's and an object's ``name``, a release's name and
version (read back from a downloaded ``manifest.json``) all end up as a folder or file name
(``WORKDIR/scenes/<scene>/``, ``objects/<object>/``, ``<name>_bundle_000001.zip``, the serve
cache's ``<name>-<version>-<digest>/``). A name with a slash, ``..`` or a leading dot would put
that folder somewhere else; so every such name passes :func:`folder_name_problem` first.

A relative path read from a file someone else made (a zip member's name, a file a bundle's
manifest lists) passes :func:`relative_path_problem` before it is joined to a folder; a path that
is then opened on disk (an import's images and points file, a bundle folder a release packs)
goes through :func:`contained_path`, the one containment rule: the name passes
:func:`relative_path_problem`, no part of the path below its folder is a symbolic link, and the
result resolves inside the folder.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated

from pydantic import AfterValidator

from brave6d.core.errors import DataError

#: Letters, digits and ``_ . + -``; starts with a letter, digit or ``_`` (so never ``.``, ``..``,
#: a hidden file or something a command line reads as a flag); at most 100 characters.
FOLDER_NAME_PATTERN = r"^[A-Za-z0-9_][A-Za-z0-9_.+-]{0,99}$"
_FOLDER_NAME = re.compile(FOLDER_NAME_PATTERN)
FOLDER_NAME_RULE = ("letters, digits and _ . + - only, starting with a letter, digit or _, "
                    "at most 100 characters")


def folder_name_problem(value: object) -> str | None:
    """Why ``value`` may not be used as one part of a path, or None when it may."""
    if not isinstance(value, str):
        return f"a name (string) is required, got {type(value).__name__}"
    if _FOLDER_NAME.fullmatch(value) is None:
        shown = repr(value) if len(value) <= 60 else repr(value[:57] + "...")
        return f"{shown} is not a folder-safe name ({FOLDER_NAME_RULE})"
    return None


def check_folder_name(value: object, where: str) -> str:
    """``value`` when it is a folder-safe name; else :class:`DataError` naming ``where`` (file and field)."""
    problem = folder_name_problem(value)
    if problem is not None:
        raise DataError(f"{where}: {problem}")
    assert isinstance(value, str)
    return value


def _folder_name_or_value_error(value: str) -> str:
    problem = folder_name_problem(value)
    if problem is not None:
        raise ValueError(problem)  # pydantic reports it at the field: "file: field 'x': <problem>"
    return value


#: The type of a model field whose value becomes a path part (the specs' names, a dataset's version).
FolderName = Annotated[str, AfterValidator(_folder_name_or_value_error)]


def relative_path_problem(path: object, *, folder_slash: bool = False) -> str | None:
    """Why the relative POSIX path ``path`` might lead outside the folder it is joined to, or None
    when it cannot: no absolute path, backslash, ``:`` (a drive letter or a Windows stream), empty,
    ``.`` or ``..`` part, control character, part ending in a dot or a space (Windows drops those, so
    ``a.`` would become ``a``), part over 255 bytes or path over 4095 bytes. ``folder_slash``: one
    trailing ``/`` (a zip's folder entry) is allowed."""
    if not isinstance(path, str) or not path:
        return "an empty name"
    if path.startswith("/"):
        return "an absolute path"
    if "\\" in path:
        return "a backslash (a Windows path separator)"
    if ":" in path:
        return "a ':' (a drive letter or a Windows stream name)"
    if len(path.encode("utf-8", "surrogatepass")) > 4095:
        return "a name longer than 4095 bytes"
    for part in (path[:-1] if folder_slash and path.endswith("/") else path).split("/"):
        if not part:
            return "an empty path part ('//')"
        if part in (".", ".."):
            return f"a '{part}' path part"
        if not part.isprintable():
            return "a control or non-printable character"
        if part.endswith((".", " ")):
            return "a path part ending in a dot or a space"
        if len(part.encode("utf-8", "surrogatepass")) > 255:
            return "a path part longer than 255 bytes"
    return None


def contained_path(root: Path | str, name: object, where: str) -> Path:
    """``root / name`` once it cannot lead outside ``root``: ``name`` passes
    :func:`relative_path_problem` (no absolute path, no ``..``), no part of the path below
    ``root`` is a symbolic link (whether it exists or not), and it resolves inside ``root``. Else
    :class:`DataError` naming ``where`` (the file and field that named it). ``root`` itself is
    the caller's (a folder the user named) and may be a link."""
    problem = relative_path_problem(name)
    if problem is not None:
        shown = repr(name) if not isinstance(name, str) or len(name) <= 80 else repr(name[:77] + "...")
        raise DataError(f"{where}: {shown} has {problem}; only files inside {root} are read")
    assert isinstance(name, str)
    base = Path(root)
    path = base
    for part in name.split("/"):
        path = path / part
        if path.is_symlink():
            raise DataError(f"{where}: {path} is a symbolic link; only files inside {root} are read, "
                            "put the file itself there")
    if not path.resolve().is_relative_to(base.resolve()):
        raise DataError(f"{where}: {path} lies outside {root}; only files inside it are read")
    return path
