"""The ``rosgate`` command: run, check, plugins, keygen, pubkey, and the commands plugins add.

A problem the user can fix is printed as one message (file, line, key, fix) with exit status 2;
tracebacks are kept for bugs.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import faulthandler
import logging
import os
import signal
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from . import __version__
from .commands import CORE_COMMANDS, stop_on_signals, wait_for_signal
from .errors import ConfigError, RosgateError

if TYPE_CHECKING:
    from .cipher import Cipher
    from .engine import Engine
    from .plugins import Plugins

EXIT_USAGE = 2
# glibc's malloc (mallopt): blocks up to M_MMAP_THRESHOLD (its most, 32 MiB) come from its heaps,
# and a heap keeps up to M_TRIM_THRESHOLD free before it gives memory back to the kernel
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
KEEP_BUFFERS = 32 * 1024 * 1024


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser, commands = _parser()
    verb = next((a for a in argv if not a.startswith("-")), None)
    if verb not in CORE_COMMANDS:  # a plugin's, or help: only then are all plugins loaded
        for name, registration in sorted(_all_plugins().commands.items()):
            command = registration.command
            sub = commands.add_parser(name, help=f"{command.help} ({registration.distribution})")
            command.arguments(sub)
            sub.set_defaults(run=command.run)
    args = parser.parse_args(argv)
    # a one-shot verb's answer is its output: only warnings join it on stderr (a path's MTU,
    # said at INFO, is news for a running bridge, not for check)
    quiet = args.command in ("check", "plugins", "keygen", "pubkey")
    level = logging.DEBUG if getattr(args, "verbose", False) else \
        logging.WARNING if quiet else logging.INFO
    # a running bridge's lines carry the time to the millisecond (ISO 8601, local time with its
    # offset), so a reconnect can be timed from the log alone; a one-shot verb's are its answer
    stamp = "" if quiet else "%(asctime)s.%(msecs)03d%(tz)s "
    logging.basicConfig(level=level, format=f"{stamp}[%(who)s] %(levelname)s %(message)s",
                        datefmt="%Y-%m-%dT%H:%M:%S", stream=sys.stderr)
    for handler in logging.getLogger().handlers:
        handler.addFilter(_STAMP)
    try:
        return int(args.run(args))
    except RosgateError as exc:
        print(f"rosgate: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except ImportError as exc:  # a library a plugin imports where it uses it, installed but broken
        from .plugins import failed_import

        failure = failed_import(exc)
        if failure is None:
            raise  # the core's own: a bug, with its traceback
        print(f"rosgate: error: plugin {failure.plugin!r} ({failure.distribution}) failed to "
              f"load: {failure.reason}\n  fix: repair or reinstall {failure.distribution}",
              file=sys.stderr)
        return EXIT_USAGE


class _Stamp(logging.Filter):
    """Gives a log record the local time's offset from UTC (``+0100``, as ISO 8601 writes it)
    and who says it: ``rosgate``, then ``rosgate robot1`` once a bridge's file is read, so the
    lines of several bridges in one journal or one terminal tell apart."""

    who = "rosgate"

    def filter(self, record: logging.LogRecord) -> bool:
        record.tz = time.strftime("%z", time.localtime(record.created))
        record.who = self.who
        return True


_STAMP = _Stamp()


def _parser() -> tuple[argparse.ArgumentParser, Any]:
    """rosgate's own commands (:data:`rosgate.commands.CORE_COMMANDS`)."""
    parser = argparse.ArgumentParser(prog="rosgate",
                                     description="A pluggable ROS 2 network bridge.")
    parser.add_argument("--version", action="version", version=f"rosgate {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    run = commands.add_parser("run", help="bridge the topics of a bringup.yaml until stopped")
    run.add_argument("file", help="the bringup.yaml")
    run.add_argument("--domain-id", type=int, default=None,
                     help="ROS domain id (default: ROS_DOMAIN_ID, else 0)")
    run.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    run.set_defaults(run=cmd_run)

    check = commands.add_parser("check", help="validate a bringup.yaml and exit")
    check.add_argument("file")
    check.set_defaults(run=cmd_check)

    plugins = commands.add_parser("plugins",
                                  help="list installed plugins, and the ones that failed to load")
    plugins.add_argument("--options", metavar="NAME",
                         help="print the options a plugin takes under plugins: NAME:")
    plugins.set_defaults(run=cmd_plugins)

    keygen = commands.add_parser("keygen", help="write a new key (mode 0600): 'identity' for a "
                                                "bridge's identity, or a cipher's name")
    keygen.add_argument("cipher", help="identity, or the cipher's name, e.g. fernet")
    keygen.add_argument("--out", help="the key file to write (default: CIPHER.key)")
    keygen.add_argument("--force", action="store_true", help="replace an existing file")
    keygen.set_defaults(run=cmd_keygen)

    pubkey = commands.add_parser("pubkey", help="print the public key of an identity file")
    pubkey.add_argument("file")
    pubkey.set_defaults(run=cmd_pubkey)
    assert tuple(commands.choices) == CORE_COMMANDS
    return parser, commands


def _all_plugins() -> Plugins:
    """Every plugin loaded; one that failed to load is named on stderr."""
    from .plugins import Plugins

    plugins = Plugins.discover()
    plugins.load_all()
    for f in plugins.failures:
        print(f"rosgate: warning: plugin {f.plugin!r} ({f.distribution}) failed to load: "
              f"{f.reason}", file=sys.stderr)
    return plugins


def _engine(path: str, plugins: Plugins | None = None, domain_id: int | None = None) -> Engine:
    from .config import load
    from .engine import Engine
    from .policy import advice, broad_rules

    engine = Engine(load(path), plugins, domain_id=domain_id).prepare()
    if (warning := engine.insecure_warning()) is not None:
        logging.getLogger("rosgate").warning(warning)
    for said in [*advice(engine.config), *broad_rules(engine.config.clients, engine.config.file)]:
        logging.getLogger("rosgate").warning(said)
    return engine


def cmd_check(args: argparse.Namespace) -> int:
    from .budget import report
    from .bus import BusTransport

    # every plugin: one this file does not use may still be one the next file needs
    engine = _engine(args.file, _all_plugins())

    def speaks(p: Any) -> str:
        """The convention a bus entry follows, for the line that lists it."""
        if not isinstance(p.transport, BusTransport):
            return ""
        return engine.resolver.bus_role(p.transport, "").speaks(p.transport, p.config) or ""

    cfg, plan = engine.config, engine.plan
    assert plan is not None
    print(f"{args.file}: ok ({cfg.role} {cfg.name!r}, {len(cfg.topics)} topic(s)"
          + (f", {len(cfg.services)} service(s)" if cfg.services else "")
          + (f", {len(cfg.actions)} action(s)" if cfg.actions else "")
          + (f", {len(cfg.clients)} client(s))" if cfg.clients else ")"))
    for p in [*plan.topics, *plan.services]:
        print(_entry_line(p.name, p.key or p.config.remote, p.config, speaks(p)))
    for a in plan.actions:  # three services and two topics each (rosgate.actions)
        calls = a.parts[0]  # its send_goal: on a bus, its key shows theirs
        where = calls.key.removesuffix("send_goal") + "*" if calls.key else a.config.remote
        print(_entry_line(a.config.action, where, a.config, speaks(calls)))
    for line in _pattern_lines(cfg, plan):
        print(line)
    for line in report(plan):
        print(line)
    for name, policy in cfg.clients.items():
        print(*_policy_lines(name, policy), sep="\n")
    return 0


#: what a rule's direction (the client's) lets a client do, by kind of entry
_MAY = {"topics": {"transmit": "send", "receive": "take", "both": "send and take"},
        "services": {"transmit": "call", "receive": "serve", "both": "call and serve"},
        "actions": {"transmit": "send goals to", "receive": "serve goals of",
                    "both": "send and serve goals of"}}


def _policy_lines(client: str, policy: Any) -> list[str]:
    """What a server lets one client bridge, a line per rule:
    ``  robot1 may send topic /robot1/**  [geometry_msgs/msg/*]  ciphers any, main port only``"""
    lines = []
    for kind in ("topics", "services", "actions"):
        for rule in getattr(policy, kind):
            types = ", ".join(rule.types) if rule.types is not None else "any type"
            ports = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in rule.ports)
            lines.append(f"  {client} may {_MAY[kind][rule.direction]} {kind[:-1]} {rule.name}  "
                         f"[{types}]  ciphers {', '.join(rule.ciphers or ['any'])}, "
                         + (f"ports {ports}" if ports else "main port only"))
    return lines or [f"  {client} may bridge nothing (no rules: every entry refused)"]


#: seconds ``check`` listens to its domain's graph at most before it says what patterns match
#: now, and how long the graph must stay the same before then (DDS discovers nodes in its time)
GRAPH_WAIT, GRAPH_QUIET = 4.0, 1.0


def _settled_graph(look: Any) -> dict[str, dict[str, set[str]]]:
    """What ``look`` finds of each kind (topics, services, actions), once it stays the same."""
    deadline, graph, since = time.monotonic() + GRAPH_WAIT, look(), time.monotonic()
    while time.monotonic() < deadline:
        time.sleep(0.1)
        now = look()
        if now != graph:
            graph, since = now, time.monotonic()
        elif any(graph.values()) and time.monotonic() - since >= GRAPH_QUIET:
            break
    return graph


def _pattern_lines(cfg: Any, plan: Any) -> list[str]:
    """Each pattern entry, and what it matches in this domain's graph now (when ROS is here)."""
    if not plan.patterns:
        return []
    from .bus import BusTransport
    from .discovery import GRAPHS, OWN_NAMESPACE, Discovery

    def on_bus(p: Any) -> bool:  # it takes what its bus announces, not this domain's graph
        return p.checked is not None and isinstance(p.checked.transport, BusTransport)

    graph: dict[str, dict[str, set[str]]] | None = None
    with contextlib.suppress(Exception):  # no ROS here: what it matches is found when it runs
        if not all(on_bus(p) for p in plan.patterns):
            from .ros import RosNode

            node = RosNode(f"check_{os.getpid()}", namespace=OWN_NAMESPACE)
            try:
                graph = _settled_graph(lambda: {kind: look(node.node)
                                                for kind, (look, _) in GRAPHS.items()})
            finally:
                node.close()
    taken: dict[str, list[str]] = {}
    for kind in GRAPHS:  # what each pattern that finds names on this side takes of its kind's
        for name, items in Discovery(cfg, plan.patterns, None, lambda f: None, lambda f: None,
                                     time.monotonic, kind=kind).matching(
                                         (graph or {}).get(kind, {})).items():
            taken.setdefault(name, []).extend(items)
    lines = []
    for p in plan.patterns:
        c = p.entry
        lines.append(_entry_line(p.name, c.remote, dataclasses.replace(
            c, type=c.type or "type from the graph"), "pattern"))
        found = taken.get(p.name, [])
        if on_bus(p):
            lines.append(f"    takes the topics announced on {c.transport} under it, as they "
                         "appear")
        elif graph is None:
            lines.append("    matches names as they appear (no ROS graph here to look at now)")
        elif not found:
            lines.append("    matches nothing in this domain now; names are bridged as they "
                         "appear")
        lines += [f"    now: {item}" for item in found]
    return lines


def _entry_line(name: str, where: str, c: Any, speaks: str) -> str:
    """``  /chatter -> base  [std_msgs/msg/String] udp cdr aead`` (and a bus dialect's name)"""
    arrow = "->" if c.direction == "transmit" else "<-"
    port = f":{c.port}" if c.port else ""
    return (f"  {name} {arrow} {where}  [{c.type}] {c.transport}{port} {c.codec} {c.cipher}"
            + (f"  ({speaks})" if speaks else ""))


def keep_large_buffers() -> None:
    """Let glibc's malloc keep up to :data:`KEEP_BUFFERS` of the megabyte buffers a bridge goes
    through per image, instead of returning each to the kernel and faulting the next one in a
    page at a time (256 page faults per megabyte, most of a bridge's CPU per image). Left alone
    where the environment sets MALLOC_*_THRESHOLD_, and where the C library is not glibc."""
    if "MALLOC_MMAP_THRESHOLD_" in os.environ or "MALLOC_TRIM_THRESHOLD_" in os.environ:
        return
    import ctypes

    with contextlib.suppress(OSError):
        libc = ctypes.CDLL(None)
        if hasattr(libc, "gnu_get_libc_version"):
            libc.mallopt(_M_MMAP_THRESHOLD, KEEP_BUFFERS)
            libc.mallopt(_M_TRIM_THRESHOLD, KEEP_BUFFERS)


#: Fast DDS's ways of naming a profile of its own: where one says something, rosgate says nothing
FASTDDS_PROFILES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")


def large_shared_memory() -> Path | None:
    """Have Fast DDS publish this bridge's messages through a shared-memory segment of 8 MiB
    (rosgate's ``fastdds.xml``) instead of its 512 kB: a larger message goes over Fast DDS's UDP
    transport, where a best-effort subscriber of this machine loses it whole with any fragment
    (a 1 MB image, about 6 times in 10). Returns the profile it set; None where the middleware
    is not Fast DDS or the environment or the working folder already gives Fast DDS a profile."""
    if not os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp").startswith("rmw_fastrtps") \
            or any(os.environ.get(name) for name in FASTDDS_PROFILES) \
            or Path("DEFAULT_FASTRTPS_PROFILES.xml").exists():
        return None
    profile = Path(__file__).with_name("fastdds.xml")
    os.environ[FASTDDS_PROFILES[0]] = str(profile)
    return profile


def cmd_run(args: argparse.Namespace) -> int:
    keep_large_buffers()
    profile = large_shared_memory()
    engine = _engine(args.file, domain_id=args.domain_id)
    _STAMP.who = f"rosgate {engine.config.name}"
    signals = stop_on_signals(signal.SIGHUP)  # SIGHUP: a server applies its clients: again
    # kill -USR1 <pid>: every thread's stack to stderr, from C, even when a thread holds the GIL
    # (for a bridge that does not stop or does not answer)
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    engine.start()
    if profile is not None:
        logging.getLogger("rosgate").info(
            "Fast DDS: publishing through an 8 MiB shared-memory segment (%s), so that messages "
            "up to that size reach best-effort subscribers whole; set %s to use a profile of "
            "your own", profile, FASTDDS_PROFILES[0])
    try:
        while wait_for_signal(signals) == signal.SIGHUP:
            engine.reload(args.file)  # SIGHUP: the server's policy, from the file as it is now
    finally:
        logging.getLogger("rosgate").info("stopping")
        engine.stop()
    return 0


def cmd_plugins(args: argparse.Namespace) -> int:
    from .plugins import Plugins

    plugins = Plugins.discover()
    if args.options:
        return _print_options(plugins, args.options)
    rows = sorted([(r.kind, r.name, r.distribution, r.version) for r in plugins.all()]
                  + [("command", name, c.distribution, c.version)
                     for name, c in plugins.commands.items()])
    for line in _columns([("KIND", "NAME", "DISTRIBUTION", "VERSION"), *rows]):
        print(line)
    for failure in plugins.failures:
        print(f"failed to load plugin {failure.plugin!r} ({failure.distribution}): "
              f"{failure.reason}")
    for name in plugins.blocked:
        print(f"blocked plugin {name!r} (ROSGATE_DISABLE_PLUGINS)")
    return 0


def _print_options(plugins: Any, name: str) -> int:
    from .options import declared, spell

    found = [r for r in plugins.all() if r.name == name]
    if not found:
        installed = ", ".join(sorted({r.name for r in plugins.all()}))
        raise ConfigError(f"no plugin is named {name!r} (installed: {installed})", file="plugins")
    for r in found:
        print(f"{r.kind} {r.name} ({r.distribution} {r.version}), under plugins: {r.name}:")
        rows = [(o.name, spell(o.type), o.default_text(),
                 o.doc + (f" ({o.limits()})" if o.limits() else "")) for o in declared(r.cls)]
        header = ("OPTION", "TYPE", "DEFAULT", "DESCRIPTION")
        for line in _columns([header, *rows]) if rows else ["no options"]:
            print("  " + line)
    return 0


def _columns(rows: Sequence[tuple[str, ...]]) -> list[str]:
    """Rows as lines, each column as wide as its widest cell (the last one as it is)."""
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]) - 1)]
    # widths has no entry for the last cell: zip stops one short of the row
    return ["  ".join([cell.ljust(width) for cell, width in zip(row, widths, strict=False)]
                      + [row[-1]])
            for row in rows]


def cmd_keygen(args: argparse.Namespace) -> int:
    from .plugins import Plugins

    if args.cipher == "identity":
        from . import identity

        path, private = Path(args.out or "identity.key"), identity.generate()
        with _new_key_file(path):
            identity.write_private(path, private, args.force)
        print(f"wrote a new identity to {path} (mode 0600); its public key, for the other side's "
              "file (server_key: on a client, clients: NAME: key: on a server):", file=sys.stderr)
        print(identity.encode(identity.public_of(private)))
        return 0
    plugins = Plugins.discover()
    registration = plugins.get("cipher", args.cipher)
    if registration is None:
        message, fix = plugins.explain_missing("cipher", args.cipher)
        raise ConfigError(message, fix=fix, file="keygen")
    cipher: type[Cipher] = registration.cls
    key = cipher.generate_key()
    if key is None:
        raise ConfigError(f"cipher {args.cipher!r} takes no key", file="keygen")
    from .identity import write_secret

    path = Path(args.out or f"{args.cipher}.key")
    with _new_key_file(path):
        write_secret(path, key + b"\n", args.force)
    print(f"wrote a new {args.cipher} key to {path} (mode 0600)")
    return 0


@contextlib.contextmanager
def _new_key_file(path: Path) -> Iterator[None]:
    """Writing a key file: an existing one, or a folder that cannot be written, said as such."""
    try:
        yield
    except FileExistsError:
        raise ConfigError(f"{path} exists; not replacing a key", file="keygen",
                          fix="pass --force to replace it, or choose another --out") from None
    except OSError as exc:
        raise ConfigError(f"cannot write {path}: {exc.strerror}", file="keygen") from None


def cmd_pubkey(args: argparse.Namespace) -> int:
    from . import identity

    path = Path(args.file)
    try:
        key = identity.load_private(path)
    except identity.IdentityError as exc:
        raise ConfigError(str(exc), file=str(path), fix=exc.fix) from None
    print(identity.encode(identity.public_of(key)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
