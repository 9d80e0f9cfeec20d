"""The installed plugins as an entry asks for them: each made once per name, with its options
from the file's ``plugins:`` table (and an entry's own over them); a plugin that is not here, or
an option it refuses, is a :class:`~rosgate.errors.ConfigError` located at the key that asked.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable
from typing import Any

from ..bus import BusRole, BusTransport
from ..cipher import Cipher
from ..config import BridgeConfig
from ..errors import ConfigError, OptionError
from ..options import parse
from ..plugins import Plugins, Registration
from ..transform import Transform
from ..transport import Transport
from ..wire.framing import DEFAULT_MAX_MESSAGE

ErrorMaker = Callable[..., ConfigError]


class PluginMaker:
    """The plugins a bridge's entries use, made once per name."""

    def __init__(self, config: BridgeConfig, plugins: Plugins):
        self.config = config
        self.plugins = plugins
        self.transports: dict[str, Transport] = {}
        self.ciphers: dict[str, Cipher] = {}
        self._decoders: dict[int, Transform | None] = {}
        self._decoders_lock = threading.Lock()

    def plugin(self, kind: str, name: str, key: str,
               error: ErrorMaker | None = None) -> Registration:
        registration = self.plugins.get(kind, name)
        if registration is None:
            message, fix = self.plugins.explain_missing(kind, name)
            raise (error or self.config.error)(key, message, fix)
        return registration

    def transport(self, name: str, key: str, error: ErrorMaker | None = None) -> Transport:
        if name not in self.transports:
            self.transports[name] = self._made("transport", name, key, error)
        return self.transports[name]

    def _made(self, kind: str, name: str, key: str, error: ErrorMaker | None, *args: Any,
              own: dict[str, Any] | None = None) -> Any:
        """A plugin made with its options from the file and ``own`` (and ``args``)."""
        cls = self.plugin(kind, name, key, error).cls
        options = self._plugin_options(cls, name, own or {}, key, error or self.config.error)
        try:
            return cls(options, *args)
        except OptionError as exc:
            raise self.option_error(name, exc, key, error) from None

    def _entry_cipher(self, name: str, key: str, error: ErrorMaker,
                      on_bus: bool = False) -> tuple[type[Cipher], Cipher | None]:
        """An entry's cipher class, and an instance keyed from the file (None in a session,
        where the session keys it: its key options are not needed). A bus has no peer to
        handshake with: its entries keep the file's keys."""
        cls: type[Cipher] = self.plugin("cipher", name, key, error).cls
        session = self.config.secure and not on_bus
        if not session or not cls.session_key_size:
            if session and cls.authenticates:
                raise error(key, f"cipher {name!r} cannot be keyed from a session",
                            "pick a cipher that can (aead, nacl, fernet)")
            if name not in self.ciphers:  # static (or keyless: none)
                self.ciphers[name] = self._made("cipher", name, key, error, self.config.base_dir)
            return cls, self.ciphers[name]
        return cls, None

    def _options(self, plugin: str) -> Any:
        return self.config.plugins.get(plugin) or {}

    def option_error(self, plugin: str, exc: OptionError, asked_by: str,
                     error: ErrorMaker | None = None) -> ConfigError:
        """Locate a plugin's complaint at its option, or, when the file has no options for the
        plugin at all, at the key that asked for the plugin."""
        if f"plugins.{plugin}" not in self.config.lines:
            return (error or self.config.error)(asked_by, f"{plugin}: {exc.message}", exc.fix)
        key = f"plugins.{plugin}" + (f".{exc.key}" if exc.key else "")
        return self.config.error(key, exc.message, exc.fix)

    def _plugin_options(self, cls: type, name: str, own: dict[str, Any], asked_by: str,
                        error: ErrorMaker) -> Any:
        """Its ``plugins:`` table, with what an entry gives (``compression: {zstd: {level: 19}}``)
        over it; a mistake is located where it was written."""
        try:
            return parse(cls, {**self._options(name), **own}, self.config.base_dir)
        except OptionError as exc:
            if exc.key is not None and exc.key in own:
                raise error(f"{asked_by}.{name}.{exc.key}", exc.message, exc.fix) from None
            raise self.option_error(name, exc, asked_by, error) from None

    def transform_for(self, wire_id: int) -> Transform | None:
        """The transform a receiver decodes a payload of ``wire_id`` with (options from this
        file's ``plugins:`` table), made once; None when no installed transform has that id."""
        with self._decoders_lock:
            if wire_id not in self._decoders:
                self._decoders[wire_id] = None
                found = self.plugins.by_wire("transform", wire_id)
                if found is not None:
                    with contextlib.suppress(OptionError):  # check reports it; frames are counted
                        options = parse(found.cls, self._options(found.name), self.config.base_dir)
                        self._decoders[wire_id] = found.cls(options, DEFAULT_MAX_MESSAGE)
            return self._decoders[wire_id]

    def bus_role(self, transport: BusTransport, key: str,
                 error: ErrorMaker | None = None) -> type[BusRole]:
        """The bus role that wires ``transport``'s entries; a :class:`ConfigError` at ``key``
        naming the distribution to install when it is not here."""
        found = self.plugins.get("bus_role", transport.role)
        if found is None:
            message, fix = self.plugins.explain_missing("bus_role", transport.role)
            raise (error or self.config.error)(
                key, f"{transport.name} is a bus, whose entries a bus role wires: {message}", fix)
        return found.cls
