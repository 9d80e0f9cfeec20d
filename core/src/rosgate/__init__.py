"""rosgate: a pluggable ROS 2 network bridge.

The API for plugin authors is what this module exports, with :mod:`rosgate.hookspecs`,
:mod:`rosgate.options` and :mod:`rosgate.keys`. Tree codecs map messages with
``rosgate_message_tree``; a plugin's tests run the plugin kit, ``rosgate_testing``.
"""

from .cipher import Cipher
from .codec import Codec
from .commands import Command
from .errors import CipherError, CodecError, ConfigError, LinkError, OptionError, RosgateError
from .hookspecs import hookimpl
from .monitor import Monitor
from .options import option
from .packetizer import Packetizer, PacketLink
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

__all__ = [
    "Address", "Cipher", "CipherError", "Codec", "CodecError", "Command", "ConfigError",
    "DatagramEndpoint", "DatagramTransport", "FastDatagramEndpoint", "FastStreamConnection",
    "LinkError", "Monitor", "OptionError", "PacketLink", "Packetizer", "RosgateError",
    "SocketConnection", "SocketListener", "StreamConnection", "StreamListener", "StreamTransport",
    "Transform", "TransformError", "Transport", "check_ip_address", "hookimpl", "ip_source_hosts",
    "option", "parse_host_port",
]
__version__ = "0.1.0"
