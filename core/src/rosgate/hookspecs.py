"""The hooks a rosgate plugin implements. This module is the plugin author's reference.

A plugin is a module registered in the entry-point group ``rosgate``::

    [project.entry-points.rosgate]
    can = "rosgate_transport_can"

that defines one or more of the functions below, decorated with :data:`rosgate.hookimpl`.
Each hook hands the plugin a ``register`` callback: call it once per class you provide. The core
owns the names: two plugins registering the same name is reported, and the second is skipped.
Hooks are always called with keyword arguments, so an implementation may omit parameters it
does not use, and new parameters can be added without breaking existing plugins.
"""

from __future__ import annotations

from typing import Callable

import pluggy

from .cipher import Cipher
from .codec import Codec
from .transport import Transport

hookspec = pluggy.HookspecMarker("rosgate")
hookimpl = pluggy.HookimplMarker("rosgate")


@hookspec
def rosgate_transports(register: Callable[[type[Transport]], None]) -> None:
    """Register transport classes (links). Called once, when plugins are loaded."""


@hookspec
def rosgate_codecs(register: Callable[[type[Codec]], None]) -> None:
    """Register codec classes (message <-> bytes). Called once, when plugins are loaded."""


@hookspec
def rosgate_ciphers(register: Callable[[type[Cipher]], None]) -> None:
    """Register cipher classes (seal/open frames). Called once, when plugins are loaded."""
