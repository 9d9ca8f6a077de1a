"""The node's own message and service types (package ``brave6d_msgs``) without a catkin build.

The definitions ship as text beside this module (``msg/*.msg``, ``srv/*.srv``). At run time
genpy's code generator (the one catkin runs) turns them into a Python package in a cache
folder keyed by the definitions' hash, which is appended to ``sys.path`` and imported: both the
node and any agent (``rosservice``, ``rostopic`` included, when that folder is on their
``PYTHONPATH``) then use the same classes and MD5 sums as a catkin-built ``brave6d_msgs``.

The definitions of the standard types they use (``std_msgs/Header``, ``geometry_msgs/Pose``...)
are taken from the installed Python classes' ``_full_text``, so no ``ros-*-msgs`` source
package is needed.
"""

from __future__ import annotations

import hashlib
import importlib
import os
import shutil
import sys
import tempfile
from pathlib import Path
from types import ModuleType
from typing import NamedTuple

from brave6d.ros_interface.ros1.ros_env import require_ros1

PACKAGE = "brave6d_msgs"
HERE = Path(__file__).resolve().parent
MSG_DIR = HERE / "msg"
SRV_DIR = HERE / "srv"
#: Standard types the definitions use, by the Python module that has each one's class.
DEPENDENCIES = {"std_msgs/Header": "std_msgs.msg", "geometry_msgs/Pose": "geometry_msgs.msg",
                "geometry_msgs/Point": "geometry_msgs.msg", "geometry_msgs/Quaternion": "geometry_msgs.msg"}
SEPARATOR = "=" * 80


class Brave6dMsgs(NamedTuple):
    msg: ModuleType
    srv: ModuleType
    path: Path  # the folder to put on PYTHONPATH to import ``brave6d_msgs``


def _definition_files() -> list[Path]:
    return sorted(MSG_DIR.glob("*.msg")) + sorted(SRV_DIR.glob("*.srv"))


def _digest() -> str:
    import genpy

    h = hashlib.sha256(getattr(genpy, "__version__", "").encode())
    for p in _definition_files():
        h.update(p.name.encode() + b"\0" + p.read_bytes())
    return h.hexdigest()[:16]


def _own_definition(full_text: str) -> str:
    """A message class's own definition: ``_full_text`` up to the first embedded dependency."""
    return full_text.split("\n" + SEPARATOR + "\n", 1)[0].rstrip() + "\n"


def _write_dependencies(root: Path) -> dict[str, list[str]]:
    """Write the standard types' ``.msg`` files under ``root``; genpy's search path for them."""
    search: dict[str, list[str]] = {PACKAGE: [str(MSG_DIR)]}
    for full, module in DEPENDENCIES.items():
        pkg, name = full.split("/")
        cls = getattr(importlib.import_module(module), name)
        folder = root / pkg / "msg"
        folder.mkdir(parents=True, exist_ok=True)
        (folder / f"{name}.msg").write_text(_own_definition(cls._full_text), encoding="utf-8")
        search[pkg] = [str(folder)]
    return search


def _generate(out: Path) -> None:
    from genpy.generator import MsgGenerator, SrvGenerator

    search = _write_dependencies(out / "_deps")
    pkg = out / PACKAGE
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("", encoding="utf-8")
    for kind, generator, files in (("msg", MsgGenerator(), sorted(MSG_DIR.glob("*.msg"))),
                                   ("srv", SrvGenerator(), sorted(SRV_DIR.glob("*.srv")))):
        if generator.generate_messages(PACKAGE, [str(f) for f in files], str(pkg / kind), search) != 0:
            raise RuntimeError(f"genpy could not generate {PACKAGE}/{kind} from {[f.name for f in files]}")
        lines = [f"from ._{f.stem} import *" for f in files]
        (pkg / kind / "__init__.py").write_text("\n".join(lines) + "\n", encoding="utf-8")


def cache_root() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(tempfile.gettempdir(), f"brave6d-{os.getuid()}")
    return Path(base) / "brave6d" / "ros1_msgs"


def load_messages(cache: Path | None = None) -> Brave6dMsgs:
    """Generate (once per definition hash) and import ``brave6d_msgs.msg`` / ``.srv``."""
    require_ros1()
    root = (cache or cache_root()) / _digest()
    if not (root / PACKAGE / "srv" / "__init__.py").is_file():
        root.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=".staging-", dir=root.parent))
        try:
            _generate(staging)
            try:
                os.rename(staging, root)  # atomic: a concurrent process may have won, which is fine
            except OSError:
                if not (root / PACKAGE / "srv" / "__init__.py").is_file():
                    raise
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    if str(root) not in sys.path:
        sys.path.append(str(root))
    msg = importlib.import_module(f"{PACKAGE}.msg")
    srv = importlib.import_module(f"{PACKAGE}.srv")
    if not Path(msg.__file__ or "").resolve().is_relative_to(root.resolve()):
        raise RuntimeError(f"another {PACKAGE} ({msg.__file__}) shadows the generated one in {root}")
    return Brave6dMsgs(msg, srv, root)
