"""The part of :mod:`brave6d.ros_interface.ros2.interfaces` that runs inside the ROS 2 Python.

Run by path with the target environment's interpreter (it needs only the standard library and,
for ``generate``, the rosidl wheels; not brave6d, which that interpreter may not see):

* ``probe DIST MODULE...`` prints JSON: where the environment keeps its files, the missing
  modules among ``MODULE...``, the installed version of ``DIST`` and where ``tf2_msgs`` comes from;
* ``versions DIST...`` prints JSON: ``{dist: installed version or null}``;
* ``generate SPEC.json`` runs the rosidl generators (C structs, Python, the typesupports) on one
  interface package, as ``rosidl generate`` would. The generator classes are called directly:
  the ROS wheels ship each entry point twice (dist-info and egg-info), which ``rosidl`` refuses,
  and the msg/srv -> IDL step is done with rosidl_adapter's converters, whose CLI wrapper needs
  catkin_pkg.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import importlib.util
import json
import os
import sys
import sysconfig
from pathlib import Path
from typing import Any

#: Where tf2_msgs comes from: not importable, our generated one, or another (ROS's).
TF2_ABSENT, TF2_OURS, TF2_REAL = "absent", "ours", "real"


def installed_state(dist: str) -> dict[str, Any]:
    """The installed version of ``dist`` (None if absent) and the source of the importable
    ``tf2_msgs``: absent, ``dist``'s own, or another (a real ROS tf2_msgs)."""
    try:
        distribution = importlib.metadata.distribution(dist)
        version: str | None = distribution.version
        ours = Path(str(distribution.locate_file("tf2_msgs/__init__.py"))).resolve()
    except importlib.metadata.PackageNotFoundError:
        version, ours = None, None
    spec = importlib.util.find_spec("tf2_msgs")
    if spec is None:
        tf2 = TF2_ABSENT
    else:
        tf2 = TF2_OURS if spec.origin and Path(spec.origin).resolve() == ours else TF2_REAL
    return {"installed": version, "tf2_msgs": tf2}


def probe(dist: str, modules: list[str]) -> dict[str, Any]:
    """What a build for this interpreter needs: install prefix, site-packages, headers, wheel tag."""
    missing = [m for m in modules if importlib.util.find_spec(m) is None]
    numpy_include = None
    if importlib.util.find_spec("numpy") is not None:
        import numpy
        numpy_include = numpy.get_include()
    paths = sysconfig.get_paths()
    return {
        **installed_state(dist),
        "missing": missing,
        "prefix": sys.prefix,
        "platlib": paths["platlib"],
        "python_include": paths["include"],
        "numpy_include": numpy_include,
        "python_tag": f"cp{sys.version_info.major}{sys.version_info.minor}",
        "platform": sysconfig.get_platform().replace("-", "_").replace(".", "_"),
    }


def versions(dists: list[str]) -> dict[str, str | None]:
    """The installed version of each of ``dists`` (None when absent)."""
    out: dict[str, str | None] = {}
    for dist in dists:
        try:
            out[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            out[dist] = None
    return out


def generate(spec: dict[str, Any]) -> None:
    """Generate one package's sources under ``spec['output']``/{c,py,typesupport_c,fastrtps_c,
    introspection_c}/<package> (so each of those dirs is an include root), from the .msg/.srv
    files ``spec['files']`` (relative to ``spec['root']``), with the dependencies' share dirs
    ``spec['includes']``."""
    from rosidl_adapter.msg import convert_msg_to_idl
    from rosidl_adapter.srv import convert_srv_to_idl
    from rosidl_generator_c.cli import GenerateC
    from rosidl_generator_py.cli import GeneratePython
    from rosidl_typesupport_c.cli import GenerateCTypesupport
    from rosidl_typesupport_fastrtps_c.cli import GenerateFastRTPSCTypesupport
    from rosidl_typesupport_introspection_c.cli import GenerateIntrospectionCTypesupport

    package, root, output = spec["package"], Path(spec["root"]), Path(spec["output"])
    idl_root = output / "idl"
    idl_files = []
    for rel in map(Path, spec["files"]):
        convert = convert_msg_to_idl if rel.suffix == ".msg" else convert_srv_to_idl
        idl = convert(root, package, rel, idl_root / rel.parent)
        idl_files.append(f"{idl_root}:{idl.relative_to(idl_root).as_posix()}")
    # rosidl_generator_py imports only the rosidl_typesupport_c module; the dispatch library
    # finds the fastrtps / introspection typesupport libraries at run time.
    extensions = [
        ("c", GenerateC("c")),
        ("py", GeneratePython("py", typesupport_implementations=["rosidl_typesupport_c"])),
        ("typesupport_c", GenerateCTypesupport("c", typesupport_implementations=[
            "rosidl_typesupport_fastrtps_c", "rosidl_typesupport_introspection_c"])),
        ("fastrtps_c", GenerateFastRTPSCTypesupport("fastrtps_c")),
        ("introspection_c", GenerateIntrospectionCTypesupport("introspection_c")),
    ]
    for subdir, extension in extensions:
        extension.generate(package, idl_files, spec["includes"], output_path=output / subdir / package)


def main(argv: list[str]) -> int:
    if argv[:1] == ["probe"] and len(argv) >= 2:
        print(json.dumps(probe(argv[1], argv[2:])))
        return 0
    if argv[:1] == ["versions"]:
        print(json.dumps(versions(argv[1:])))
        return 0
    if argv[:1] == ["generate"] and len(argv) == 2:
        spec = json.loads(Path(argv[1]).read_text())
        os.environ["AMENT_PREFIX_PATH"] = sys.prefix  # the generators find their templates by it
        with contextlib.redirect_stdout(sys.stderr):  # the converters print every file they write
            generate(spec)
        return 0
    print("usage: _rosidl_generate.py probe DIST [MODULE...] | versions DIST... | generate SPEC.json",
          file=sys.stderr)
    return 2


if __name__ == "__main__":
    # Run by path, Python puts this file's directory first on sys.path; it holds the tf2_msgs/
    # definitions folder, which would then import as a namespace package.
    here = Path(__file__).resolve().parent
    sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != here]
    sys.exit(main(sys.argv[1:]))
