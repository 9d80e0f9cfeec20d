"""The hooks a rosgate plugin implements. This module is the plugin author's reference.

A plugin is a module registered in the entry-point group ``rosgate``::

    [project.entry-points.rosgate]
    can = "rosgate_transport_can"

that defines one or more of the functions below. Every function of it named ``rosgate_*`` is
taken for a hook implementation (marked with :data:`rosgate.hookimpl` or not): a name that
matches no hook (``rosgate_transport``) makes the plugin fail to load, as ``rosgate plugins``
says. Each hook hands a ``register`` callback, called once per class provided; two plugins
registering one name are reported and the second is skipped. Hooks are called once, when the
plugin loads, always with keyword arguments (omit the parameters you do not use); one that
raises fails the plugin, keeping nothing it registered. Results are not used.

A plugin module may say which version of the plugin API it was written for
(``ROSGATE_API = 2``, see :data:`API_VERSION`); a newer one than this rosgate serves is refused
by name, with the version.
"""

from __future__ import annotations

from collections.abc import Callable

import pluggy

from .bus import BusRole
from .cipher import Cipher
from .codec import Codec
from .commands import Command
from .monitor import Monitor
from .packetizer import Packetizer
from .service_framing import ServiceFraming
from .transform import Transform
from .transport import Transport

#: the plugin API's version: what ``rosgate`` exports (``rosgate.__all__``) and the hooks here.
#: 1 was the first release's; what changed since, with the one-line fix, is docs/plugin-api.md
API_VERSION = 2

hookspec = pluggy.HookspecMarker("rosgate")
hookimpl = pluggy.HookimplMarker("rosgate")


@hookspec
def rosgate_transports(register: Callable[[type[Transport]], None]) -> None:
    """Register transport classes (links): subclasses of :class:`rosgate.DatagramTransport`,
    :class:`rosgate.StreamTransport` or :class:`rosgate.bus.BusTransport`."""


@hookspec
def rosgate_bus_roles(register: Callable[[type[BusRole]], None]) -> None:
    """Register bus roles: subclasses of :class:`rosgate.bus.BusRole`, which check and wire the
    entries of the bus transports whose ``role`` names them (rosgate-fleet's ``fleet``)."""


@hookspec
def rosgate_codecs(register: Callable[[type[Codec]], None]) -> None:
    """Register codec classes (message <-> bytes): subclasses of :class:`rosgate.Codec`."""


@hookspec
def rosgate_ciphers(register: Callable[[type[Cipher]], None]) -> None:
    """Register cipher classes (seal/open frames): subclasses of :class:`rosgate.Cipher`."""


@hookspec
def rosgate_commands(register: Callable[[Command], None]) -> None:
    """Register ``rosgate`` subcommands: one :class:`rosgate.Command` each (see
    :mod:`rosgate.commands`), loaded when ``rosgate`` is asked for a verb not its own or for its
    help. A verb rosgate has (``run``, ``check``...) or another plugin took first is skipped."""


@hookspec
def rosgate_transforms(register: Callable[[type[Transform]], None]) -> None:
    """Register payload transform classes (compression, between codec and cipher): subclasses of
    :class:`rosgate.Transform`, each with a ``wire_id`` no other installed transform has."""


@hookspec
def rosgate_packetizers(register: Callable[[type[Packetizer]], None]) -> None:
    """Register packetizer classes (how a datagram link cuts frames into packets and puts them
    back together: fragments, loss recovery): subclasses of :class:`rosgate.Packetizer`, each
    with ``magic`` bytes no other installed packetizer has."""


@hookspec
def rosgate_monitors(register: Callable[[type[Monitor]], None]) -> None:
    """Register monitor classes (exporters of a running bridge's status: diagnostics, metrics):
    subclasses of :class:`rosgate.Monitor` (see :mod:`rosgate.monitor`). A monitor runs when the
    bridge's file asks for it by name."""


@hookspec
def rosgate_service_framings(register: Callable[[type[ServiceFraming]], None]) -> None:
    """Register service framings (a device's call pattern, for service entries with
    ``framing: <name>``): subclasses of :class:`rosgate.service_framing.ServiceFraming`."""
