"""``tf2_msgs/TFMessage`` for rclpy when no ``tf2_msgs`` package is installed.

PyPI's ROS 2 Kilted wheels (the ``ros`` extra) carry rclpy and the common message packages but
not ``tf2_msgs``, the package of ``/tf``'s message. :func:`load_tfmessage` imports the real
``tf2_msgs`` when there is one (a ROS installation); otherwise it generates the type support of
``TFMessage.idl`` (shipped beside this file) with the rosidl generators the wheels install
(C, Fast DDS C and introspection C type supports, the Python bindings), compiles them with the C
and C++ compilers (``CC``/``CXX``, default ``cc``/``c++``) against the wheels' headers and
libraries, caches the result in ``$MCSM_ROS_CACHE`` (default ``~/.cache/mcsm/ros2``; one folder
per Python, rclpy and geometry_msgs version) and loads it. The generated type has the same DDS
type name and the same type hash (``RIHS01_e369d0f0...``) as the real one, so tf2 listeners and
RViz read it. The first build takes a few seconds; later starts only load it.

``python -m mcsm_client.ros2.tf2`` builds (or finds) it and prints its folder.
"""

from __future__ import annotations

import ctypes
import fcntl
import hashlib
import importlib
import importlib.metadata
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
from pathlib import Path
from typing import Any

PACKAGE = "tf2_msgs"
IDL = Path(__file__).with_name("TFMessage.idl")
#: the libraries the type support dispatch opens by name (preloaded so dlopen finds them)
PRELOAD = ("rosidl_generator_c", "rosidl_typesupport_fastrtps_c",
           "rosidl_typesupport_introspection_c", "rosidl_typesupport_c",
           "rosidl_generator_py")

__all__ = ["TfBuildError", "build", "cache_dir", "load_tfmessage"]


class TfBuildError(RuntimeError):
    """The TFMessage type support could not be generated or compiled (the reason says why)."""


def _version(dist: str) -> str:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return "none"


def cache_dir() -> Path:
    """Where the build for this interpreter and these ROS wheels lives."""
    root = Path(os.environ.get("MCSM_ROS_CACHE") or Path.home() / ".cache" / "mcsm" / "ros2")
    key = "|".join((sys.prefix, sys.version, _version("ros-rclpy"),
                    _version("ros-geometry-msgs"), IDL.read_text()))
    return root / f"{PACKAGE}-{hashlib.sha256(key.encode()).hexdigest()[:16]}"


def load_tfmessage() -> Any:
    """The ``TFMessage`` class: the installed one, else the cached or a fresh build.

    Raises
    ------
    TfBuildError
        Nothing installed and the build failed (no compiler, no generators).
    """
    try:
        from tf2_msgs.msg import TFMessage  # a ROS installation has it

        return TFMessage
    except ImportError:
        pass
    d = build()
    for lib in PRELOAD:
        # RTLD_GLOBAL under the library's soname: the dispatch's dlopen("lib...so") finds it
        ctypes.CDLL(str(d / "lib" / f"lib{PACKAGE}__{lib}.so"), mode=ctypes.RTLD_GLOBAL)
    sys.path.insert(0, str(d / "py"))
    importlib.invalidate_caches()
    mod = importlib.import_module(f"{PACKAGE}.msg")
    return mod.TFMessage


def build() -> Path:
    """The cached build's folder, building it first if needed (one process at a time)."""
    d = cache_dir()
    if (d / "ok").exists():
        return d
    d.parent.mkdir(parents=True, exist_ok=True)
    with open(d.parent / f"{d.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if (d / "ok").exists():
            return d
        tmp = Path(tempfile.mkdtemp(prefix=f"{d.name}-", dir=d.parent))
        try:
            _build_into(tmp)
            (tmp / "ok").write_text("built\n")
            shutil.rmtree(d, ignore_errors=True)
            tmp.rename(d)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    return d


def _generate(out: Path) -> None:
    """Run the rosidl generators (in this interpreter; called in a child process)."""
    from rosidl_generator_c.cli import GenerateC
    from rosidl_generator_py.cli import GeneratePython
    from rosidl_typesupport_c.cli import GenerateCTypesupport
    from rosidl_typesupport_fastrtps_c.cli import GenerateFastRTPSCTypesupport
    from rosidl_typesupport_introspection_c.cli import GenerateIntrospectionCTypesupport

    src = out / "src" / "msg"
    src.mkdir(parents=True)
    shutil.copy(IDL, src / "TFMessage.idl")
    files = [f"{out / 'src'}:msg/TFMessage.idl"]
    include = [str(Path(sys.prefix) / "share")]
    for name, cls in (("c", GenerateC), ("fastrtps_c", GenerateFastRTPSCTypesupport),
                      ("introspection_c", GenerateIntrospectionCTypesupport),
                      ("typesupport_c", GenerateCTypesupport), ("py", GeneratePython)):
        gen = out / "gen" / name
        gen.mkdir(parents=True)
        cls(name).generate(PACKAGE, files, include, gen)


def _run(cmd: list[str], what: str) -> None:
    r = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if r.returncode != 0:
        tail = (r.stderr or r.stdout).strip().splitlines()[-5:]
        raise TfBuildError(f"{what} failed ({' '.join(cmd[:2])} ...): " + " | ".join(tail))


def _build_into(out: Path) -> None:
    env_py = [sys.executable, "-c",
              "import sys; from pathlib import Path; "
              "from mcsm_client.ros2.tf2 import _generate; _generate(Path(sys.argv[1]))",
              str(out)]
    r = subprocess.run(env_py, capture_output=True, text=True, check=False,
                       env={**os.environ, "AMENT_PREFIX_PATH": sys.prefix})
    if r.returncode != 0:
        tail = r.stderr.strip().splitlines()[-3:]
        raise TfBuildError("generating tf2_msgs/TFMessage failed (are the ROS wheels of the "
                           "'ros' extra installed?): " + " | ".join(tail))
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    cxx = os.environ.get("CXX") or shutil.which("c++") or shutil.which("g++")
    if not cc or not cxx:
        raise TfBuildError("building tf2_msgs/TFMessage needs a C and a C++ compiler "
                           "(Debian: apt-get install gcc g++)")
    import numpy

    prefix = Path(sys.prefix)
    gen = out / "gen"
    inc_dir = out / "include" / PACKAGE / "msg"
    inc_dir.parent.mkdir(parents=True)
    shutil.copytree(gen / "c" / "msg", inc_dir)
    for ts in ("fastrtps_c", "introspection_c"):
        shutil.copytree(gen / ts / "msg", inc_dir, dirs_exist_ok=True)
    lib = out / "lib"
    pkg = out / "py" / PACKAGE
    lib.mkdir()
    (pkg / "msg").mkdir(parents=True)
    includes = [f"-I{out / 'include'}", f"-I{prefix / 'include'}",
                *(f"-I{p}" for p in sorted((prefix / "include").iterdir()) if p.is_dir()),
                f"-I{sysconfig.get_paths()['include']}", f"-I{numpy.get_include()}"]
    links = [f"-L{lib}", f"-L{prefix / 'lib'}", "-Wl,-rpath,$ORIGIN"]
    base = ["-shared", "-fPIC", "-O2", "-w"]

    def so(compiler: str, sources: list[Path], name: str, libs: list[str],
           extra: list[str] | None = None) -> None:
        target = lib / f"lib{PACKAGE}__{name}.so"
        _run([compiler, *base, *(extra or []), *includes, *map(str, sources), "-o", str(target),
              f"-Wl,-soname,{target.name}", *links, *(f"-l{x}" for x in libs)],
             f"compiling {target.name}")

    own = f"{PACKAGE}__rosidl_generator_c"
    so(cc, sorted((gen / "c" / "msg" / "detail").glob("*.c")), "rosidl_generator_c",
       ["geometry_msgs__rosidl_generator_c", "rosidl_runtime_c", "rcutils"])
    so(cxx, sorted((gen / "fastrtps_c" / "msg" / "detail").glob("*.cpp")),
       "rosidl_typesupport_fastrtps_c",
       [own, "geometry_msgs__rosidl_typesupport_fastrtps_c", "geometry_msgs__rosidl_generator_c",
        "rosidl_typesupport_fastrtps_c", "rosidl_typesupport_fastrtps_cpp", "fastcdr",
        "rosidl_runtime_c", "rcutils", "rmw"], ["-std=c++17"])
    so(cc, sorted((gen / "introspection_c" / "msg" / "detail").glob("*.c")),
       "rosidl_typesupport_introspection_c",
       [own, "geometry_msgs__rosidl_typesupport_introspection_c", "rosidl_runtime_c"])
    so(cxx, sorted((gen / "typesupport_c" / "msg").glob("*.cpp")), "rosidl_typesupport_c",
       [own, "rosidl_typesupport_c", "rosidl_runtime_c", "rcpputils", "rcutils"], ["-std=c++17"])
    so(cc, sorted((gen / "py" / "msg").glob("*_s.c")), "rosidl_generator_py",
       [own, "geometry_msgs__rosidl_generator_py", "geometry_msgs__rosidl_generator_c",
        "rosidl_runtime_c"])
    ext = pkg / f"{PACKAGE}_s__rosidl_typesupport_c.so"
    _run([cc, *base, *includes, str(gen / "py" / f"_{PACKAGE}_s.ep.rosidl_typesupport_c.c"),
          "-o", str(ext), f"-L{lib}", f"-L{prefix / 'lib'}", "-Wl,-rpath,$ORIGIN/../../lib",
          f"-l{PACKAGE}__rosidl_generator_py", f"-l{PACKAGE}__rosidl_typesupport_c", f"-l{own}",
          "-lrosidl_runtime_c"], "compiling the Python extension")
    (pkg / "__init__.py").write_text("")
    for f in (gen / "py" / "msg").glob("*.py"):
        shutil.copy(f, pkg / "msg" / f.name)
    shutil.rmtree(gen)
    shutil.rmtree(out / "src")


if __name__ == "__main__":
    try:
        print(build())
    except TfBuildError as exc:
        print(f"mcsm_client.ros2.tf2: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
