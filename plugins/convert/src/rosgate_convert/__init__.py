"""``rosgate convert OLD.yaml``: a ros2_socket_bridge ``bringup.yaml`` becomes a rosgate client
file (written) and the server's part (printed, or written with ``--server-out``), with one line
per thing that did not carry over as it was, naming the old file's line (on stderr).

The old bridge's keys were given on the command line; rosgate's are identity files: the
command writes ``<name>.key`` and ``<server>.key`` (mode 0600; kept when they exist) and puts
each one's public key in the other side's file, so both files pass ``rosgate check`` as written.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

import yaml

from rosgate import Command, ConfigError, hookimpl, identity_public_key

from .legacy import Converted, convert


def arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("old", metavar="OLD.yaml", help="the old client's bringup.yaml")
    parser.add_argument("-o", "--out", default="rosgate.yaml",
                        help="the client file to write (default: rosgate.yaml)")
    parser.add_argument("--server-out", metavar="FILE",
                        help="also write the server's file there (default: print it)")
    parser.add_argument("--name", default="robot1", help="the client bridge's name")
    parser.add_argument("--server-name", default="server", help="the server bridge's name")
    parser.add_argument("--force", action="store_true", help="replace existing output files")


def _identity(path: Path) -> str:
    """The public key of the identity at ``path``, made first if there is none."""
    try:
        return identity_public_key(path, make=True)
    except ValueError as exc:
        raise ConfigError(str(exc), file=str(path), fix=getattr(exc, "fix", None)) from None


def _write(path: Path, header: str, data: dict, force: bool) -> None:
    if path.exists() and not force:
        raise ConfigError(f"{path} exists; not replacing it", file="rosgate convert",
                          fix="pass --force, or choose another -o / --server-out")
    path.write_text(header + yaml.safe_dump(data, sort_keys=False, width=100), encoding="utf-8")


def run(args: argparse.Namespace) -> int:
    old = Path(args.old)
    try:
        text = old.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read it: {exc.strerror or exc}", file=str(old)) from None
    out = Path(args.out)
    folder = out.absolute().parent
    client_key, server_key = f"{args.name}.key", f"{args.server_name}.key"
    try:
        converted: Converted = convert(
            text, str(old), args.name, args.server_name, client_key, server_key,
            client_public=_identity(folder / client_key),
            server_public=_identity(folder / server_key))
    except yaml.YAMLError as exc:
        raise ConfigError(f"not YAML: {exc}", file=str(old)) from None
    header = f"# converted by rosgate convert from {old.name}\n"
    _write(out, header, converted.client, args.force)
    server_text = header + yaml.safe_dump(converted.server, sort_keys=False, width=100)
    if args.server_out:
        _write(Path(args.server_out), header, converted.server, args.force)
    for line, message in sorted(converted.notes):
        print(f"{old}:{line}: {message}", file=sys.stderr)
    topics = len(converted.client["topics"])
    print(f"wrote {out} ({topics} topic(s)); identities {folder / client_key} (this side) and "
          f"{folder / server_key} (copy it to the server, and nowhere else)", file=sys.stderr)
    if args.server_out:
        print(f"wrote {args.server_out}, the server's file", file=sys.stderr)
    else:
        print("# the server's file:")
        print(server_text, end="")
    return 0


@hookimpl
def rosgate_commands(register: Callable[[Command], None]) -> None:
    register(Command("convert", "turn a ros2_socket_bridge bringup.yaml into rosgate files", run,
                     arguments))
