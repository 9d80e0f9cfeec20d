"""rosgate: a pluggable ROS 2 network bridge.

The public API for plugin authors is what this module exports.
"""

from .cipher import Cipher
from .codec import Codec
from .errors import CipherError, CodecError, ConfigError, LinkError, OptionError, RosgateError
from .hookspecs import hookimpl
from .transport import (Address, DatagramEndpoint, SocketConnection, SocketListener,
                        StreamConnection, StreamListener, Transport, check_ip_address,
                        parse_host_port)

__all__ = [
    "Address", "Cipher", "CipherError", "Codec", "CodecError", "ConfigError", "DatagramEndpoint",
    "LinkError", "OptionError", "RosgateError", "SocketConnection", "SocketListener",
    "StreamConnection", "StreamListener", "Transport",
    "check_ip_address", "hookimpl", "parse_host_port",
]
__version__ = "0.1.0"
