"""The hooks a rosgate plugin implements. This module is the plugin author's reference.

A plugin is a module registered in the entry-point group ``rosgate``::

    [project.entry-points.rosgate]
    can = "rosgate_transport_can"

that defines one or more of the functions below. Every function of the module whose name starts
with ``rosgate_`` is taken for a hook implementation (mark it with :data:`rosgate.hookimpl`, or
not, as you like): a name that matches no hook here — ``rosgate_transport`` for
``rosgate_transports`` — makes the plugin fail to load, and ``rosgate plugins`` says why.

Each hook hands the plugin a ``register`` callback: call it once per class you provide. The core
owns the names: two plugins registering the same name is reported, and the second is skipped.
Each hook is called once per plugin, when the plugin is loaded (on first use of one of its names,
or by ``rosgate plugins``); an exception it raises makes that plugin fail to load, and nothing it
registered in that hook is kept. Hooks are always called with keyword arguments, so an
implementation may omit parameters it does not use, and new parameters can be added without
breaking existing plugins. Results are not used.
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
    """Register ``rosgate`` subcommands: one :class:`rosgate.Command` each (its name, one line of
    help, the function that adds its arguments and the one that runs it; see
    :mod:`rosgate.commands`). ``rosgate`` loads every plugin when it is asked for a verb that is
    not its own, or for its help. A verb rosgate has (``run``, ``check``...) or that another plugin
    registered first is reported and skipped."""


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
