"""Finding plugins: entry points in the group ``rosgate``, loaded one by one.

A plugin that fails to import, or whose hook raises, is recorded by name with the reason and
skipped; the others keep working. ``ROSGATE_DISABLE_PLUGINS=name,name`` blocks entry points by
name (``builtin`` cannot be blocked: the core needs ``cdr`` and ``none``).
"""

from __future__ import annotations

import os
import traceback
from dataclasses import dataclass, field
from importlib import metadata
from types import ModuleType
from typing import Any

import pluggy

from . import hookspecs
from .cipher import Cipher
from .codec import Codec
from .transport import Transport

ENTRY_POINT_GROUP = "rosgate"
DISABLE_VARIABLE = "ROSGATE_DISABLE_PLUGINS"

KINDS: dict[str, tuple[str, type]] = {
    # kind: (hook name, base class)
    "transport": ("rosgate_transports", Transport),
    "codec": ("rosgate_codecs", Codec),
    "cipher": ("rosgate_ciphers", Cipher),
}

# Names of in-tree plugins and the distribution that provides each; any other name is guessed by
# the naming convention rosgate-<kind>-<name>.
KNOWN_DISTRIBUTIONS = {
    ("transport", "udp"): "rosgate-transport-udp",
    ("transport", "tcp"): "rosgate-transport-tcp",
    ("transport", "bt"): "rosgate-transport-bt",
    ("transport", "can"): "rosgate-transport-can",
    ("codec", "msgpack"): "rosgate-codec-msgpack",
    ("codec", "cbor"): "rosgate-codec-cbor",
    ("cipher", "fernet"): "rosgate-crypto-fernet",
    ("cipher", "nacl"): "rosgate-crypto-nacl",
    ("cipher", "aead"): "rosgate-crypto-aead",
}


def distribution_for(kind: str, name: str) -> str:
    prefix = {"transport": "transport", "codec": "codec", "cipher": "crypto"}[kind]
    return KNOWN_DISTRIBUTIONS.get((kind, name), f"rosgate-{prefix}-{name}")


@dataclass(frozen=True)
class Registration:
    kind: str
    name: str
    cls: type
    plugin: str  # entry-point name (or the name given to Plugins.add)
    distribution: str
    version: str


@dataclass(frozen=True)
class Failure:
    plugin: str
    distribution: str
    reason: str


@dataclass
class Plugins:
    """Every plugin class known to this process, by kind and name."""

    registered: dict[tuple[str, str], Registration] = field(default_factory=dict)
    failures: list[Failure] = field(default_factory=list)
    blocked: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._manager = pluggy.PluginManager("rosgate")
        self._manager.add_hookspecs(hookspecs)

    # -- loading ---------------------------------------------------------------------------
    @classmethod
    def discover(cls) -> "Plugins":
        """Load every entry point in the group ``rosgate`` that is not blocked."""
        plugins = cls()
        blocked = {n.strip() for n in os.environ.get(DISABLE_VARIABLE, "").split(",") if n.strip()}
        blocked.discard("builtin")
        for ep in sorted(metadata.entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
            dist = ep.dist.name if ep.dist else "?"
            version = ep.dist.version if ep.dist else "?"
            if ep.name in blocked:
                plugins.blocked.append(ep.name)
                continue
            try:
                module = ep.load()
            except Exception as exc:  # a broken plugin must not take the others down
                plugins.failures.append(Failure(ep.name, dist, _reason(exc)))
                continue
            plugins.add(module, ep.name, dist, version)
        return plugins

    def add(self, module: ModuleType | Any, plugin: str, distribution: str = "?",
            version: str = "?") -> None:
        """Register one plugin module (or object with hook implementations) and collect what it
        registers. Tests use this to add a plugin in-process."""
        if self._manager.has_plugin(plugin):
            self.failures.append(Failure(plugin, distribution, "a plugin of this name is already loaded"))
            return
        try:
            self._manager.register(module, name=plugin)
        except Exception as exc:
            self.failures.append(Failure(plugin, distribution, _reason(exc)))
            return
        for kind, (hook_name, base) in KINDS.items():
            hook = getattr(self._manager.hook, hook_name)
            found: list[type] = []
            try:
                # call this plugin's implementation only, so an error is attributed to it;
                # like pluggy, pass only the arguments the implementation asks for
                arguments = {"register": found.append}
                for impl in hook.get_hookimpls():
                    if impl.plugin_name == plugin:
                        impl.function(*(arguments[a] for a in impl.argnames))
            except Exception as exc:
                self.failures.append(Failure(plugin, distribution, f"{hook_name}: {_reason(exc)}"))
                continue
            for cls in found:
                problem = _check_class(cls, base)
                if problem:
                    self.failures.append(Failure(plugin, distribution, problem))
                    continue
                key = (kind, cls.name)
                if key in self.registered:
                    first = self.registered[key]
                    self.failures.append(Failure(
                        plugin, distribution,
                        f"{kind} {cls.name!r} is already provided by {first.distribution}; skipped"))
                    continue
                self.registered[key] = Registration(kind, cls.name, cls, plugin, distribution, version)

    def remove(self, plugin: str) -> None:
        """Forget a plugin added with :meth:`add` (tests)."""
        self._manager.unregister(name=plugin)
        for key in [k for k, r in self.registered.items() if r.plugin == plugin]:
            del self.registered[key]

    # -- lookup ----------------------------------------------------------------------------
    def names(self, kind: str) -> list[str]:
        return sorted(n for (k, n) in self.registered if k == kind)

    def get(self, kind: str, name: str) -> Registration | None:
        return self.registered.get((kind, name))

    def explain_missing(self, kind: str, name: str) -> tuple[str, str]:
        """(message, fix) for a bringup.yaml that asks for a plugin that is not here."""
        installed = ", ".join(self.names(kind)) or "none"
        message = f"unknown {kind} {name!r} (installed {kind}s: {installed})"
        failed = [f for f in self.failures if f.plugin == name]
        if failed:
            message += f"; plugin {name!r} is installed but failed to load: {failed[0].reason}"
        if name in self.blocked:
            message += f"; plugin {name!r} is blocked by {DISABLE_VARIABLE}"
        return message, f"pip install {distribution_for(kind, name)}, or pick an installed {kind}"


def _check_class(cls: Any, base: type) -> str | None:
    if not (isinstance(cls, type) and issubclass(cls, base)):
        return f"registered {cls!r}, which is not a subclass of rosgate.{base.__name__}"
    name = getattr(cls, "name", None)
    if not isinstance(name, str) or not name.isidentifier():
        return f"{cls.__name__} has no valid 'name' (a short identifier such as 'udp')"
    return None


def _reason(exc: BaseException) -> str:
    last = traceback.extract_tb(exc.__traceback__)[-1:] if exc.__traceback__ else []
    where = f" ({last[0].filename}:{last[0].lineno})" if last else ""
    return f"{type(exc).__name__}: {exc}{where}"
