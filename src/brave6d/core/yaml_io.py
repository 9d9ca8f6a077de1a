"""The one YAML reader of the project: strict about duplicate keys and nesting depth.

``yaml.safe_load`` keeps the later of two equal keys without a word (a spec with two ``scale:``
lines silently loses one) and recurses once per nesting level, so a file nested thousands deep
ends in a RecursionError with a traceback thousands of lines long. :class:`StrictLoader` refuses
both with the line of the offending node, and :func:`read_yaml` turns every problem into one
line ``FILE:LINE:COLUMN: invalid YAML: PROBLEM``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml
from yaml.composer import ComposerError
from yaml.constructor import ConstructorError
from yaml.nodes import MappingNode, Node

from brave6d.core.errors import BraveError, DataError
from brave6d.core.json_input import DEFAULT_LIMITS

#: Deepest nesting accepted (scene specs and 3D-DAT files use fewer than ten levels).
MAX_DEPTH = 100
#: Largest YAML file read (a scene spec or a dataset.yaml is a few kB; 3D-DAT's files a few MB).
MAX_YAML_BYTES = 64 * 2**20
_MERGE_TAG = "tag:yaml.org,2002:merge"


class StrictLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses duplicate mapping keys and nesting deeper than :data:`MAX_DEPTH`."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent: Node | None, index: Any) -> Node | None:
        """Compose one node, counting how deep it sits (PyYAML's composer recurses per level)."""
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                event = self.peek_event()
                raise ComposerError(None, None, f"nested deeper than {MAX_DEPTH} levels", event.start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node: MappingNode, deep: bool = False) -> dict[Any, Any]:
        """Construct a mapping, refusing a key that appears twice (``<<`` merges may still override)."""
        first_line: dict[Any, int] = {}
        for key_node, _ in node.value:
            if key_node.tag == _MERGE_TAG:
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                seen = first_line.get(key)
            except TypeError:  # unhashable key: the base class reports it
                continue
            if seen is not None:
                raise ConstructorError("while constructing a mapping", node.start_mark,
                                       f"duplicate key {key!r} (first at line {seen})", key_node.start_mark)
            first_line[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep=deep)

    def construct_yaml_int(self, node: Node) -> int:
        """An integer, its literal no longer than JSON's limit (CPython refuses >4300 digits with a ValueError)."""
        _check_number(node)
        return super().construct_yaml_int(node)  # type: ignore[no-any-return]

    def construct_yaml_float(self, node: Node) -> float:
        """A float, its literal no longer than JSON's limit."""
        _check_number(node)
        return super().construct_yaml_float(node)  # type: ignore[no-any-return]


def _check_number(node: Node) -> None:
    """Refuse a number literal longer than the JSON reader's limit (:mod:`brave6d.core.json_input`)."""
    limit = DEFAULT_LIMITS.max_number_chars
    if len(str(node.value)) > limit:
        raise ConstructorError(None, None, f"a number of {len(str(node.value))} characters (at most {limit} are read)",
                               node.start_mark)


StrictLoader.add_constructor("tag:yaml.org,2002:int", StrictLoader.construct_yaml_int)
StrictLoader.add_constructor("tag:yaml.org,2002:float", StrictLoader.construct_yaml_float)


def parse_yaml(text: str) -> Any:
    """Parse YAML text with :class:`StrictLoader` (raises ``yaml.YAMLError``)."""
    return yaml.load(text, Loader=StrictLoader)  # noqa: S506 - StrictLoader is a SafeLoader


def yaml_problem(exc: yaml.YAMLError) -> tuple[str, str]:
    """(``:LINE:COLUMN`` or ``""``, problem) of a YAML error, for one-line messages."""
    mark = getattr(exc, "problem_mark", None)
    where = f":{mark.line + 1}:{mark.column + 1}" if mark is not None else ""
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    return where, problem


def read_yaml(path: Path | str, shown: str | None = None,
              error: Callable[[str], BraveError] = DataError) -> Any:
    """Read a UTF-8 YAML file strictly; any problem raises ``error`` with one line naming the file.

    ``shown`` is how the file is named in messages (default: the path as given). A missing file
    is ``FILE: file not found``; bad YAML is ``FILE:LINE:COLUMN: invalid YAML: PROBLEM``; a file
    that is no regular file (a FIFO, a device) or holds over :data:`MAX_YAML_BYTES` is refused unread.
    """
    from brave6d.core.bounded_files import read_regular

    p = Path(path)
    name = str(p) if shown is None else shown
    data = read_regular(p, MAX_YAML_BYTES, name, "YAML", error)
    try:
        return parse_yaml(data.decode("utf-8"))
    except yaml.YAMLError as exc:
        where, problem = yaml_problem(exc)
        raise error(f"{name}{where}: invalid YAML: {problem}") from None
    except UnicodeDecodeError as exc:
        raise error(f"{name}: not UTF-8 text ({exc.reason})") from None
