"""Finding plugins: entry points in the group ``rosgate``, loaded when first asked for.

Asking for a plugin loads the entry point of that name first (by convention named like the class
it registers), the others only if the class is not there (python-can's model); listing and
unknown verbs load them all. Transforms and packetizers are also found by what they put on the
wire (``wire_id``, ``magic``), which no two installed plugins may share.

As pytest does with ``pytest_``, every ``rosgate_*`` function of a plugin is a hook
implementation, so ``check_pending`` catches a misspelt hook. A plugin that fails (import, hook,
class) is recorded as a :class:`Failure` naming it and skipped; ``ROSGATE_DISABLE_PLUGINS``
blocks entry points by name (not ``builtin``: the core needs ``cdr`` and ``none``).
"""

from __future__ import annotations

import inspect
import os
import threading
import traceback
import types
from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata
from typing import Any

import pluggy

from . import hookspecs
from .bus import BusRole, BusTransport
from .cipher import Cipher
from .codec import Codec
from .commands import Command, command_problem
from .monitor import Monitor
from .options import declaration_problem, did_you_mean
from .packetizer import RESERVED_MAGIC, Packetizer
from .service_framing import ServiceFraming
from .transform import Transform
from .transport import DatagramTransport, StreamTransport, Transport

ENTRY_POINT_GROUP = "rosgate"
DISABLE_VARIABLE = "ROSGATE_DISABLE_PLUGINS"
BUILTIN = "builtin"
HOOK_PREFIX = "rosgate_"

#: each kind's base class; its hook is ``rosgate_<kind>s``
KINDS: dict[str, type] = {
    "transport": Transport, "codec": Codec, "cipher": Cipher, "transform": Transform,
    "packetizer": Packetizer, "monitor": Monitor, "service_framing": ServiceFraming,
    "bus_role": BusRole,
}
#: the word of a kind in distribution names, where it is not the kind itself
_DISTRIBUTION_WORD = {"cipher": "crypto", "transform": "compress", "packetizer": "recovery"}
#: the plugins rosgate's own distributions provide under names the convention does not give
_OWN_DISTRIBUTIONS = {("packetizer", "fec"): "rosgate-recovery",
                      ("packetizer", "retransmit"): "rosgate-recovery",
                      ("service_framing", "serial_datagram"): "rosgate-mcu-cvra",
                      ("bus_role", "fleet"): "rosgate-fleet",
                      ("packetizer", "compact"): "rosgate-compact"}


def distribution_hint(kind: str, name: str) -> str:
    """Which distribution to install for a plugin that is not here: rosgate's own where one
    provides it, else the one the naming convention gives, ``rosgate-<kind>-<name>``."""
    own = _OWN_DISTRIBUTIONS.get((kind, name))
    return own or f"by convention rosgate-{_DISTRIBUTION_WORD.get(kind, kind)}-{name}"


def wire_keys(kind: str, cls: Any) -> list[tuple[str, Any]]:
    """What a plugin class is recognised by on the wire, besides its name."""
    if kind == "transform":
        return [(kind, cls.wire_id)]
    if kind == "packetizer":
        return [(kind, bytes(m)) for m in cls.magic]
    return []


@dataclass(frozen=True)
class Registration:
    kind: str
    name: str
    cls: type
    plugin: str  # entry-point name (or the name given to Plugins.add)
    distribution: str
    version: str


@dataclass(frozen=True)
class CommandRegistration:
    command: Command
    plugin: str
    distribution: str
    version: str


@dataclass(frozen=True)
class Failure:
    plugin: str
    distribution: str
    reason: str


class PluginManager(pluggy.PluginManager):
    """pluggy's manager with pytest's rule: each ``rosgate_*`` function is a hook implementation."""

    def __init__(self) -> None:
        super().__init__("rosgate")
        self.add_hookspecs(hookspecs)

    def parse_hookimpl_opts(self, plugin: Any, name: str) -> pluggy.HookimplOpts | None:
        if not name.startswith(HOOK_PREFIX):
            return None  # and nothing else is looked at, as pytest does
        opts = super().parse_hookimpl_opts(plugin, name)
        value = inspect.getattr_static(plugin, name, None)
        if opts is None and (inspect.isfunction(value) or isinstance(
                value, (staticmethod, classmethod, types.MethodType))):
            opts = pluggy.HookimplOpts(wrapper=False, hookwrapper=False, optionalhook=False,
                                       tryfirst=False, trylast=False, specname=None)
        return opts


class Plugins:
    """Every plugin class this process knows of, by kind and name, loaded as asked for."""

    def __init__(self, blocked: list[str] | None = None) -> None:
        self.manager = PluginManager()
        self.registered: dict[tuple[str, str], Registration] = {}
        self.commands: dict[str, CommandRegistration] = {}  # rosgate <name>, from plugins
        #: (kind, wire id or magic) -> the registration that claimed it
        self.on_wire: dict[tuple[str, Any], Registration] = {}
        self.failures: list[Failure] = []
        self.blocked: list[str] = list(blocked or [])
        self._waiting: list[metadata.EntryPoint] = []  # found, not loaded yet
        self._lock = threading.RLock()  # a server prepares its clients' topics in their threads

    @classmethod
    def discover(cls) -> Plugins:
        """List the entry points (importing none but the core's own)."""
        plugins = cls()
        blocked = {n.strip() for n in os.environ.get(DISABLE_VARIABLE, "").split(",") if n.strip()}
        blocked.discard(BUILTIN)
        for ep in sorted(metadata.entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
            if ep.name in blocked:
                plugins.blocked.append(ep.name)
            else:
                plugins._waiting.append(ep)
        plugins.load_all(BUILTIN)
        return plugins

    def load_all(self, name: str | None = None) -> None:
        """Load the entry points not loaded yet (only those named ``name``, when given)."""
        with self._lock:
            while waiting := [ep for ep in self._waiting if name in (None, ep.name)]:
                self._load(waiting[0])

    def _load(self, ep: metadata.EntryPoint) -> None:
        self._waiting.remove(ep)
        distribution, version = (ep.dist.name, ep.dist.version) if ep.dist else ("?", "?")
        try:
            module = ep.load()
        except Exception as exc:  # a broken plugin must not take the others down
            self.failures.append(Failure(ep.name, distribution, _reason(exc)))
            return
        self.add(module, ep.name, distribution, version)

    def add(self, module: types.ModuleType | Any, plugin: str, distribution: str = "?",
            version: str = "?") -> None:
        """Register a plugin module (or any hashable object with hooks) and collect what it
        registers (tests add plugins in-process with it)."""
        def fail(reason: str) -> None:
            self.failures.append(Failure(plugin, distribution, reason))

        with self._lock:
            if self.manager.has_plugin(plugin):
                return fail("a plugin of this name is already loaded")
            written_for = getattr(module, "ROSGATE_API", hookspecs.API_VERSION)
            if not isinstance(written_for, int) or written_for > hookspecs.API_VERSION:
                return fail(f"written for rosgate plugin API {written_for!r}; this rosgate "
                            f"serves API {hookspecs.API_VERSION}: upgrade rosgate")
            try:
                self.manager.register(module, name=plugin)
            except Exception as exc:  # pluggy refuses a hook taking arguments the spec lacks
                return fail(_reason(exc))
            try:
                self.manager.check_pending()
            except pluggy.PluginValidationError as exc:
                unknown = sorted(c.name for c in self.manager.get_hookcallers(exc.plugin) or []
                                 if not c.has_spec())
                self.manager.unregister(exc.plugin)
                return fail(_misspelt(unknown) if unknown else str(exc))
            for kind, base in KINDS.items():
                for cls in self._call(module, f"{HOOK_PREFIX}{kind}s", fail):
                    problem = _check_class(cls, base) or self._clash(kind, cls)
                    if problem:
                        fail(problem)
                        continue
                    registration = Registration(kind, cls.name, cls, plugin, distribution, version)
                    self.registered[(kind, cls.name)] = registration
                    for wire in wire_keys(kind, cls):
                        self.on_wire[wire] = registration
            for command in self._call(module, "rosgate_commands", fail):
                problem = command_problem(command)
                if problem is None and command.name in self.commands:
                    problem = (f"command {command.name!r} is already provided by "
                               f"{self.commands[command.name].distribution}; skipped")
                if problem:
                    fail(problem)
                    continue
                self.commands[command.name] = CommandRegistration(command, plugin, distribution,
                                                                  version)

    def _call(self, module: Any, hook_name: str, fail: Callable[[str], None]) -> list[Any]:
        """What ``module``'s own implementation of a hook registers; nothing when it raises."""
        found: list[Any] = []
        others = [p for p in self.manager.get_plugins() if p is not module]
        try:
            self.manager.subset_hook_caller(hook_name, remove_plugins=others)(
                register=found.append)
        except Exception as exc:
            fail(f"{hook_name}: {_reason(exc)}")
            return []
        return found

    def _clash(self, kind: str, cls: Any) -> str | None:
        """Why ``cls`` cannot have its name or its wire id (magic)."""
        first = self.registered.get((kind, cls.name))
        if first is not None:
            return f"{kind} {cls.name!r} is already provided by {first.distribution}; skipped"
        claimed = [self.on_wire[w] for w in wire_keys(kind, cls) if w in self.on_wire]
        if claimed:
            what = "wire_id" if kind == "transform" else "magic"
            return (f"{kind} {cls.name!r} has the {what} of {claimed[0].name!r} "
                    f"({claimed[0].distribution}); skipped")
        return None

    def remove(self, plugin: str) -> None:
        """Forget a plugin added with :meth:`add` (tests)."""
        with self._lock:
            self.manager.unregister(name=plugin)
            tables: tuple[dict[Any, Any], ...] = (self.registered, self.commands, self.on_wire)
            for table in tables:
                for key in [k for k, r in table.items() if r.plugin == plugin]:
                    del table[key]

    def get(self, kind: str, name: str) -> Registration | None:
        """The plugin class of that kind and name: the entry point named ``name`` loaded first,
        every other one if the class is not there."""
        with self._lock:
            if (kind, name) not in self.registered:
                self.load_all(name)
            if (kind, name) not in self.registered:
                self.load_all()
            return self.registered.get((kind, name))

    def by_wire(self, kind: str, wire: Any) -> Registration | None:
        """The transform of a ``wire_id``, the packetizer of a ``magic`` (loads all if unknown)."""
        with self._lock:
            if (kind, wire) not in self.on_wire:
                self.load_all()
            return self.on_wire.get((kind, wire))

    def all(self) -> list[Registration]:
        """Every plugin class, all loaded, by kind then name."""
        self.load_all()
        return sorted(self.registered.values(), key=lambda r: (r.kind, r.name))

    def names(self, kind: str) -> list[str]:
        return [r.name for r in self.all() if r.kind == kind]

    def explain_missing(self, kind: str, name: str, named: bool = True) -> tuple[str, str]:
        """(message, fix) for a plugin a file names, or (``named`` False) its choices need."""
        installed = ", ".join(self.names(kind)) or "none"
        what = kind.replace("_", " ")
        message = f"unknown {what} {name!r} (installed {what}s: {installed})"
        # a file names no bus role: the bus transport does, so there is none to pick
        pick = f", or pick an installed {what}" if named and kind != "bus_role" else ""
        failed = [f for f in self.failures if f.plugin == name]
        if failed:
            message += f"; plugin {name!r} is installed but failed to load: {failed[0].reason}"
            return message, f"repair or reinstall {failed[0].distribution}{pick}"
        if name in self.blocked:
            message += f"; plugin {name!r} is blocked by {DISABLE_VARIABLE}"
            return message, f"remove {name} from {DISABLE_VARIABLE}{pick}"
        return message, (f"pip install the distribution that provides it "
                         f"({distribution_hint(kind, name)}){pick}")


_installed: Plugins | None = None
_installed_lock = threading.Lock()


def installed() -> Plugins:
    """The plugins of this environment, discovered once (where links look up what came)."""
    global _installed
    with _installed_lock:
        if _installed is None:
            _installed = Plugins.discover()
        return _installed


def failed_import(exc: ImportError) -> Failure | None:
    """The plugin whose module made the innermost call of an ImportError: plugins import slow
    libraries where they use them, so a broken one fails there, not when the plugin loads."""
    packages = {ep.value.split(":")[0].split(".")[0]: ep
                for ep in metadata.entry_points(group=ENTRY_POINT_GROUP) if ep.name != BUILTIN}
    frames = traceback.walk_tb(exc.__traceback__)
    names = [str(frame.f_globals.get("__name__", "")).split(".")[0] for frame, _ in frames]
    ep = next((packages[name] for name in reversed(names) if name in packages), None)
    return None if ep is None else Failure(ep.name, ep.dist.name if ep.dist else "?", _reason(exc))


def _check_class(cls: Any, base: type) -> str | None:
    if not (isinstance(cls, type) and issubclass(cls, base)):
        return f"registered {cls!r}, which is not a subclass of rosgate.{base.__name__}"
    name = getattr(cls, "name", None)
    if not isinstance(name, str) or not name.isidentifier():
        return f"{cls.__name__} has no valid 'name' (a short identifier such as 'udp')"
    if inspect.isabstract(cls):
        missing = sorted(getattr(cls, "__abstractmethods__", ()))
        return f"{cls.__name__} does not implement {', '.join(missing)}"
    if base is Transport and not issubclass(cls, (DatagramTransport, StreamTransport,
                                                  BusTransport)):
        return f"{cls.__name__} is no kind of link (subclass DatagramTransport, StreamTransport " \
               f"or BusTransport, since rosgate plugin API {hookspecs.API_VERSION}: " \
               "docs/plugin-api.md)"
    if base is Transform:
        wire_id = getattr(cls, "wire_id", None)
        if not isinstance(wire_id, int) or isinstance(wire_id, bool) or not 1 <= wire_id <= 255:
            return f"{cls.__name__} has no valid 'wire_id' (1..255, the byte that names it)"
    if base is Packetizer:
        magic = getattr(cls, "magic", None)
        # only a link's sole packetizer (cuts_every_frame) needs no magic to be found
        if (not isinstance(magic, tuple) or not (magic or getattr(cls, "cuts_every_frame", False))
                or not all(isinstance(m, bytes) and len(m) == 2 for m in magic)):
            return f"{cls.__name__} has no valid 'magic' (a tuple of two-byte bytes: (b'XY',))"
        if set(magic) & set(RESERVED_MAGIC):
            return f"{cls.__name__} claims a magic of the link's own " \
                   f"({', '.join(map(repr, RESERVED_MAGIC))})"
    return declaration_problem(cls)


def _misspelt(names: list[str]) -> str:
    hooks = sorted(h for h in dir(hookspecs) if h.startswith(HOOK_PREFIX))
    parts = [f"{name!r}{did_you_mean(name, hooks)[1]}" for name in names]
    return f"unknown hook {', '.join(parts)}; the hooks are {', '.join(hooks)}"


#: modules of the first release's plugin API (API 1) that moved, and where to
MOVED = {"rosgate.testing": "the plugin kit is a distribution of its own: pip install "
                            "rosgate-testing, and import rosgate_testing"}


def _reason(exc: BaseException) -> str:
    last = traceback.extract_tb(exc.__traceback__)[-1:]
    where = f" ({last[0].filename}:{last[0].lineno})" if last else ""
    text = "; ".join(line.strip() for line in str(exc).splitlines() if line.strip())
    return f"{type(exc).__name__}: {text}{where}{_api_hint(exc)}"


def _api_hint(exc: BaseException) -> str:
    """What a plugin written for an older plugin API runs into, and its fix."""
    name = getattr(exc, "name", None) if isinstance(exc, ImportError) else None
    if not name or not name.startswith("rosgate."):
        return ""
    fix = MOVED.get(name, "import what a plugin needs from rosgate itself (rosgate.__all__); "
                          "the core's other modules are not the plugin API")
    return f" — since rosgate plugin API {hookspecs.API_VERSION}: {fix} (docs/plugin-api.md)"
