"""rosgate: a pluggable ROS 2 network bridge.

The API for plugin authors is what this module exports (``__all__``), at version
:data:`API_VERSION`; every other module of the package is the core's own and may change in any
release. A change to what is exported here is a new API version, listed with its one-line fix in
docs/plugin-api.md. Tree codecs map messages with ``rosgate_message_tree``; a plugin's tests run
the plugin kit, ``rosgate_testing``.
"""

from .bus import BusRole, BusTransport, Unauthenticated
from .cipher import Cipher
from .codec import Codec
from .commands import Command, stop_on_signals, wait_for_signal
from .discovery import BusPattern
from .drops import Drop, LinkDrop, Reason, declare
from .errors import CipherError, CodecError, ConfigError, LinkError, OptionError, RosgateError
from .hookspecs import API_VERSION, hookimpl
from .keys import KeyOptions, describe_source, identity_public_key, key_source, load_key
from .monitor import Monitor, Status
from .options import option
from .packetizer import PARTIAL_COST, Packet, Packetizer, PacketLink
from .runtime import RUNTIME_VARIABLE, runtime_dir, socket_path
from .runtime import SUFFIX as SOCKET_SUFFIX
from .service_framing import ServiceFraming
from .transform import Transform, TransformError
from .transport import (
    Address,
    DatagramEndpoint,
    DatagramTransport,
    FastDatagramEndpoint,
    FastStreamConnection,
    SocketConnection,
    SocketListener,
    StreamConnection,
    StreamListener,
    StreamTransport,
    Transport,
    check_ip_address,
    ip_source_hosts,
    parse_host_port,
)
from .wire.envelope import topic_of
from .wire.framing import DEFAULT_MAX_MESSAGE, FINISHED_REMEMBERED, FRAGMENT, FramingError

__all__ = [
    "API_VERSION", "Address", "BusPattern", "BusRole", "BusTransport", "Cipher", "CipherError",
    "Codec", "CodecError", "Command", "ConfigError", "DEFAULT_MAX_MESSAGE", "DatagramEndpoint",
    "DatagramTransport", "Drop", "FINISHED_REMEMBERED", "FRAGMENT", "FastDatagramEndpoint",
    "FastStreamConnection", "FramingError", "KeyOptions", "LinkDrop", "LinkError", "Monitor",
    "OptionError", "PARTIAL_COST", "Packet", "PacketLink", "Packetizer", "RUNTIME_VARIABLE",
    "Reason", "RosgateError", "SOCKET_SUFFIX", "ServiceFraming", "SocketConnection",
    "SocketListener", "Status", "StreamConnection", "StreamListener", "StreamTransport",
    "Transform", "TransformError", "Transport", "Unauthenticated", "check_ip_address", "declare",
    "describe_source", "hookimpl", "identity_public_key", "ip_source_hosts", "key_source",
    "load_key", "option", "parse_host_port", "runtime_dir", "socket_path", "stop_on_signals",
    "topic_of", "wait_for_signal",
]
__version__ = "0.1.0"
