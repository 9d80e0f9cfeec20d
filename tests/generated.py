"""A ROS message package generated and compiled here, as colcon would build it, into a prefix
of its own: so that a test can run two bridges on two versions of one custom message.

ROS's own generators come with rclpy's wheels (``rosidl_generator_c``, ``_py``, the type
description and the C type supports); their extensions are called in-process, because the
``rosidl`` command refuses to start when two distributions declare its entry points (as the
wheels here do). ``cc``/``c++`` compile what they write against the headers and libraries of
the environment rclpy runs in; nothing is downloaded.

The prefix is laid out as an installed package: ``lib/`` (the C libraries, found by the type
support's dispatch through ``LD_LIBRARY_PATH``), ``python/`` (the Python package and its
extension, on ``PYTHONPATH``) and ``share/`` (the ament index, on ``AMENT_PREFIX_PATH``).
:func:`environment` gives a process those three variables.
"""

from __future__ import annotations

import hashlib
import json
import os
import pathlib
import shutil
import subprocess
import sys
import sysconfig
from collections.abc import Mapping

#: the C type supports generated and built, each with its own source and library; the fastrtps
#: one is what rmw_fastrtps_cpp takes, the introspection one what the others can
TYPESUPPORTS = ("rosidl_typesupport_fastrtps_c", "rosidl_typesupport_introspection_c")


class BuildError(RuntimeError):
    """A generator or compiler failed: its command and output."""


def build(prefix: pathlib.Path, package: str, messages: Mapping[str, str]) -> pathlib.Path:
    """``package`` with ``messages`` (name -> .msg text) generated and compiled into ``prefix``,
    unless a build of the very same definitions is there already (a stamp file says which)."""
    import fcntl

    stamp = prefix / "built.json"
    wanted = {"package": package, "messages": dict(messages), "python": sys.version,
              "generator": _generator_version()}
    prefix.parent.mkdir(parents=True, exist_ok=True)
    with open(prefix.parent / f".{prefix.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # two test runs at once build it once
        if stamp.exists() and json.loads(stamp.read_text()) == wanted:
            return prefix
        if prefix.exists():
            shutil.rmtree(prefix)
        _build(prefix, package, messages)
        stamp.write_text(json.dumps(wanted))
    return prefix


def _build(prefix: pathlib.Path, package: str, messages: Mapping[str, str]) -> None:
    source = prefix / "src" / package
    (source / "msg").mkdir(parents=True)
    for name, text in messages.items():
        (source / "msg" / f"{name}.msg").write_text(text)
    generated = _generate(prefix / "gen", source, package, sorted(messages))
    _compile(prefix, generated, package, sorted(messages))


def environment(prefix: pathlib.Path, base: Mapping[str, str] | None = None) -> dict[str, str]:
    """A process's environment in which ``prefix``'s package is installed (and no other copy)."""
    env = dict(os.environ if base is None else base)
    for name, path in (("PYTHONPATH", prefix / "python"), ("LD_LIBRARY_PATH", prefix / "lib"),
                       ("AMENT_PREFIX_PATH", prefix)):
        env[name] = os.pathsep.join([str(path), *filter(None, [env.get(name)])])
    # rclpy's wheels re-exec Python once to set LD_LIBRARY_PATH; let them add theirs to ours
    env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)
    return env


# -- generating ---------------------------------------------------------------------------------
def _generator_version() -> str:
    from importlib.metadata import version

    return version("rosidl_generator_c")


def _generate(out: pathlib.Path, source: pathlib.Path, package: str,
              names: list[str]) -> pathlib.Path:
    """The .msg files as IDL, their type descriptions (with the RIHS01 hashes), then every
    generator's sources, each under ``out/<generator>/<package>/`` like an include tree."""
    import inspect

    from rosidl_adapter.msg import convert_msg_to_idl
    from rosidl_cli.command.hash.api import generate_type_hashes
    from rosidl_generator_c.cli import GenerateC
    from rosidl_generator_py.cli import GeneratePython
    from rosidl_typesupport_c.cli import GenerateCTypesupport
    from rosidl_typesupport_fastrtps_c.cli import GenerateFastRTPSCTypesupport
    from rosidl_typesupport_introspection_c.cli import GenerateIntrospectionCTypesupport

    os.environ.setdefault("AMENT_PREFIX_PATH", sys.prefix)  # the generators find their templates
    idl_dir = out / "idl"
    (idl_dir / "msg").mkdir(parents=True)
    for name in names:
        convert_msg_to_idl(source, package, pathlib.Path("msg") / f"{name}.msg",
                           idl_dir / "msg")
    idl = [f"{idl_dir}:msg/{name}.idl" for name in names]
    descriptions = generate_type_hashes(package_name=package, interface_files=idl,
                                        include_paths=[], output_path=out / "type_description")
    for kind, extension in (("c", GenerateC), ("typesupport_c", GenerateCTypesupport),
                            ("rosidl_typesupport_fastrtps_c", GenerateFastRTPSCTypesupport),
                            ("rosidl_typesupport_introspection_c",
                             GenerateIntrospectionCTypesupport),
                            ("py", GeneratePython)):
        generator = extension(kind)
        extra = ({"type_description_files": descriptions} if "type_description_files" in
                 inspect.signature(generator.generate).parameters else {})
        generator.generate(package, idl, [], output_path=out / kind / package, **extra)
    return out


# -- compiling ----------------------------------------------------------------------------------
def _compile(prefix: pathlib.Path, gen: pathlib.Path, package: str, names: list[str]) -> None:
    lib, python = prefix / "lib", prefix / "python" / package
    lib.mkdir(parents=True)
    ros = pathlib.Path(sys.prefix)
    includes = [f"-I{gen / kind}" for kind in ("c", *TYPESUPPORTS, "typesupport_c")]
    includes += [f"-I{path}" for path in sorted((ros / "include").iterdir()) if path.is_dir()]
    includes += [f"-I{ros / 'include'}", f"-I{sysconfig.get_paths()['include']}"]
    links = [f"-L{lib}", f"-L{ros / 'lib'}", f"-Wl,-rpath,{lib}:{ros / 'lib'}"]

    def library(name: str, sources: list[pathlib.Path], libraries: list[str],
                out: pathlib.Path | None = None) -> None:
        cpp = any(s.suffix == ".cpp" for s in sources)
        target = out or lib / f"lib{package}__{name}.so"
        _run(["c++" if cpp else "cc", "-shared", "-fPIC", "-O1", "-w",
              *(["-std=c++17"] if cpp else []), *includes, *map(str, sources),
              "-o", str(target), *links, *[f"-l{x}" for x in libraries]])

    c = gen / "c" / package / "msg" / "detail"
    library("rosidl_generator_c", [c / f"{_snake(n)}__{part}.c" for n in names
                                   for part in ("description", "functions", "type_support")],
            ["rosidl_runtime_c", "rcutils"])
    own = f"{package}__rosidl_generator_c"
    fastrtps = gen / "rosidl_typesupport_fastrtps_c" / package / "msg" / "detail"
    library("rosidl_typesupport_fastrtps_c",
            [fastrtps / f"{_snake(n)}__type_support_c.cpp" for n in names],
            [own, "rosidl_typesupport_fastrtps_c", "rosidl_typesupport_fastrtps_cpp",
             "rosidl_runtime_c", "fastcdr", "rcutils"])
    introspection = gen / "rosidl_typesupport_introspection_c" / package / "msg" / "detail"
    library("rosidl_typesupport_introspection_c",
            [introspection / f"{_snake(n)}__type_support.c" for n in names],
            [own, "rosidl_typesupport_introspection_c", "rosidl_runtime_c"])
    dispatch = gen / "typesupport_c" / package / "msg"
    library("rosidl_typesupport_c", [dispatch / f"{_snake(n)}__type_support.cpp" for n in names],
            [own, "rosidl_typesupport_c", "rosidl_runtime_c", "rcpputils", "rcutils"])
    import numpy

    includes.append(f"-I{numpy.get_include()}")
    py = gen / "py" / package
    library("rosidl_generator_py", [py / "msg" / f"_{_snake(n)}_s.c" for n in names],
            [own, f"{package}__rosidl_typesupport_c", "rosidl_runtime_c"])
    shutil.copytree(py, python, ignore=shutil.ignore_patterns("*.c"))
    (python / "__init__.py").touch()
    suffix = sysconfig.get_config_var("EXT_SUFFIX")
    library("", [py / f"_{package}_s.ep.rosidl_typesupport_c.c"],
            [f"{package}__rosidl_generator_py", own, f"{package}__rosidl_typesupport_c",
             "rosidl_runtime_c"], out=python / f"{package}_s__rosidl_typesupport_c{suffix}")
    index = prefix / "share" / "ament_index" / "resource_index"
    for kind in ("packages", "rosidl_interfaces"):
        (index / kind).mkdir(parents=True)
    (index / "packages" / package).touch()
    (index / "rosidl_interfaces" / package).write_text(
        "\n".join(f"msg/{n}.msg" for n in names) + "\n")


def _snake(name: str) -> str:
    """``Reading`` -> ``reading``, ``NavSatFix`` -> ``nav_sat_fix`` (the generators' file names)."""
    from rosidl_pycommon import convert_camel_case_to_lower_case_underscore

    return str(convert_camel_case_to_lower_case_underscore(name))


def _run(command: list[str]) -> None:
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode:
        raise BuildError(f"{' '.join(command)}\n{done.stdout}{done.stderr}")


def digest(messages: Mapping[str, str]) -> str:
    """A short name for a set of definitions (a cache folder's)."""
    return hashlib.sha256(json.dumps(dict(messages), sort_keys=True).encode()).hexdigest()[:12]
