"""Every message that names a command-line flag names one that exists.

The source's messages (errors, warnings, hints, help texts) are read with ``ast``; every ``--flag``
in them must be an option of the program the message names: ``brave6d COMMAND [SUB]`` (the
options of that command's parser and its sub-commands'), a ``benchmarks/NAME.py`` or
``scripts/NAME`` script (its ``add_argument`` calls), or, when the message names no program, some
``brave6d`` command (a hint printed by one command about its own options). Flags of programs the
project does not own are listed with the program they belong to.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import re
from functools import lru_cache
from pathlib import Path

import pytest

from brave6d.cli import COMMANDS

ROOT = Path(__file__).resolve().parents[1]
FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*[a-z0-9]")
#: ``brave6d COMMAND [SUB]`` in a message; ``benchmarks/NAME.py`` or ``scripts/NAME``.
NAMED_COMMAND = re.compile(r"brave6d ([a-z0-9][a-z0-9-]*)(?: ([a-z][a-z0-9-]*))?")
NAMED_SCRIPT = re.compile(r"((?:benchmarks|scripts)/[\w./-]+\.(?:py|sh))")
#: Flags of other programs that messages tell the user to run (the program, then its flags).
FOREIGN = {"rosmaster": {"--core"}, "pip": {"--no-cache-dir"}}
#: Calls whose string arguments declare options rather than mention them.
DECLARING = {"add_argument", "add_parser", "add_argument_group", "add_mutually_exclusive_group", "ArgumentParser"}
#: Calls that run another program: their arguments are its command line, not a message.
RUNNING = {"Popen", "run", "call", "check_call", "check_output"}


def _walk_parser(parser: argparse.ArgumentParser, path: tuple[str, ...], out: dict[tuple[str, ...], set[str]]) -> None:
    flags = out.setdefault(path, set())
    for action in parser._actions:  # argparse keeps its options here; no public accessor
        flags.update(s for s in action.option_strings if s.startswith("--"))
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                _walk_parser(sub, path + (name,), out)


@lru_cache(maxsize=1)
def cli_flags() -> dict[tuple[str, ...], set[str]]:
    """``(command, sub, ...)`` -> the long options of that parser (its sub-commands' separately)."""
    out: dict[tuple[str, ...], set[str]] = {}
    for command in COMMANDS:
        parser = argparse.ArgumentParser(prog=f"brave6d {command.name}")
        importlib.import_module(command.module).configure(parser)
        _walk_parser(parser, (command.name,), out)
    return out


def script_flags(relative: str) -> set[str]:
    """The long options a script declares (its ``add_argument`` calls; for a shell script, the
    ``--flag`` cases it matches)."""
    path = ROOT / relative
    assert path.is_file(), f"a message names {relative}, which does not exist"
    text = path.read_text()
    if path.suffix == ".sh":
        return set(re.findall(r"^\s*(--[a-z][a-z0-9-]*)\)", text, flags=re.M)) | set(re.findall(r'"(--[a-z][a-z0-9-]*)"', text))
    flags: set[str] = set()
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "add_argument":
            flags.update(a.value for a in node.args if isinstance(a, ast.Constant) and str(a.value).startswith("--"))
    return flags


def _text(node: ast.AST) -> str:
    """The literal text of a string expression: an f-string's values and an expression become ``{}``,
    a concatenation joins its parts, a list or tuple (a command line) joins its items with spaces."""
    if isinstance(node, ast.Constant):
        return node.value if isinstance(node.value, str) else "{}"
    if isinstance(node, ast.JoinedStr):
        return "".join(_text(v) if isinstance(v, ast.Constant) else "{}" for v in node.values)
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add):
        return _text(node.left) + _text(node.right)
    if isinstance(node, (ast.List, ast.Tuple)):
        return " ".join(_text(e) for e in node.elts)
    if isinstance(node, ast.IfExp):
        return _text(node.body) + " " + _text(node.orelse)
    return "{}"


def messages() -> list[tuple[str, int, str]]:
    """``(file, line, text)`` of every string passed to a call (not declaring an option) or given as
    a ``help=`` text, in the package's source, that names a flag."""
    found = []
    for path in sorted((ROOT / "src" / "brave6d").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.Call) or getattr(node.func, "attr", getattr(node.func, "id", "")) in RUNNING:
                continue
            name = getattr(node.func, "attr", getattr(node.func, "id", ""))
            texts = [] if name in DECLARING else [_text(a) for a in node.args]
            texts += [_text(k.value) for k in node.keywords if k.arg in ("help", "epilog", "description")
                      or name not in DECLARING]
            for text in texts:
                if FLAG.search(text):
                    found.append((str(path.relative_to(ROOT)), node.lineno, text))
    return found


def unknown_flags(text: str) -> list[str]:
    """The flags of ``text`` that the program it names (module docstring) does not have."""
    everything = set().union(*cli_flags().values())
    bad = []
    for match in FLAG.finditer(text):
        flag, before = match.group(), text[:match.start()]
        foreign = [prog for prog, flags in FOREIGN.items() if prog in before and flag in flags]
        if foreign:
            continue
        scripts = NAMED_SCRIPT.findall(before)
        commands = NAMED_COMMAND.findall(before)
        if scripts and (not commands or before.rfind(scripts[-1]) > before.rfind("brave6d " + commands[-1][0])):
            known = script_flags(scripts[-1])
        elif commands:
            command, sub = commands[-1]
            known = set().union(*(f for path, f in cli_flags().items() if path[0] == command
                                  and (not sub or (command, sub) not in cli_flags() or path[:2] == (command, sub))))
            known |= cli_flags().get((command,), set())
        else:
            known = everything
        if flag not in known:
            bad.append(flag)
    return bad


def test_every_flag_a_message_names_exists() -> None:
    found = messages()
    assert len(found) > 50  # the scan sees the package's messages (not an empty walk)
    # a module that is its own program (python -m brave6d.ros_interface.ros1.example_agent) may name its own options
    wrong = [f"{file}:{line}: {flags} in {text[:160]!r}" for file, line, text in found
             if (flags := [f for f in unknown_flags(text) if f not in script_flags(file)])]
    assert not wrong, "messages name flags that do not exist:\n" + "\n".join(wrong)


@pytest.mark.parametrize("text, bad", [
    ("give it as AgentSetup(learned_model=DIR) or --learned-model DIR", ["--learned-model"]),
    ("brave6d learn train ... --modles DIR", ["--modles"]),
    ("brave6d serve: --allow-remote", []),
    ("brave6d learn heldout --detect-scales 1", []),
    ("brave6d serve --detect-scales 1", ["--detect-scales"]),  # a flag of another command
    ("python benchmarks/baselines.py --learned-model DIR", []),
    ("python benchmarks/baselines.py --no-such-flag", ["--no-such-flag"]),
    ("run rosmaster --core -p PORT", []),
])
def test_the_check_tells_real_flags_from_missing_ones(text: str, bad: list[str]) -> None:
    assert unknown_flags(text) == bad
