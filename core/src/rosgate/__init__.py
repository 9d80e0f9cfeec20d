"""rosgate: a pluggable ROS 2 network bridge.

The API for plugin authors is what this module exports (``__all__``), at version
:data:`API_VERSION`; every other module of the package is the core's own and may change in any
release. A change to what is exported here is a new API version, listed with its one-line fix in
docs/plugin-api.md. Tree codecs map messages with ``rosgate_message_tree``; a plugin's tests run
the plugin kit, ``rosgate_testing`` (the core's own library, released with it).

Besides the base classes of every plugin kind, it holds what a bus role (``rosgate-fleet``) and
a bus plugin on it (``rosgate-transport-zenoh``) or a service framing (``rosgate-mcu-cvra``)
build with: the entries they read (:class:`TopicConfig`, :class:`ServiceConfig`,
:class:`Direction`, :class:`Framing`), the specs the core hands them (:class:`TopicSpec`,
:class:`ServiceSpec`), the :class:`Link` and :class:`Sender` a bus link implements, the routes a
bus role makes (:class:`Route` and its kinds), the envelope they read (:func:`unpack_envelope`
and its flags), :func:`topic_id_for`, the ROS type helpers and the names in front of a bare
datagram (:func:`pack_name`, :func:`split_name`).
"""

from .bus import BusRole, BusTransport, Unauthenticated
from .cipher import Cipher
from .codec import Codec
from .commands import Command, stop_on_signals, wait_for_signal
from .config import Direction, Framing, ServiceConfig, TopicConfig
from .discovery import BusPattern
from .drops import Drop, LinkDrop, Reason, declare
from .errors import CipherError, CodecError, ConfigError, LinkError, OptionError, RosgateError
from .hookspecs import API_VERSION, hookimpl
from .keys import KeyOptions, describe_source, identity_public_key, key_source, load_key
from .links.base import FrameHandler, Link, NoLink, Sender
from .monitor import Monitor, Status
from .options import option
from .packetizer import PARTIAL_COST, Packet, Packetizer, PacketLink
from .rostypes import TypeNotFound, qos_profile, resolve_type, type_hash
from .routes import ReceiveRoute, Route, TransmitRoute
from .runtime import RUNTIME_VARIABLE, runtime_dir, socket_path
from .runtime import SUFFIX as SOCKET_SUFFIX
from .service_framing import ServiceFraming
from .services import Call, CallerRoute, ServerRoute, ServiceRoute
from .spec import ServiceSpec, TopicSpec
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
from .warn import BUGS
from .wire.envelope import (
    FLAG_ANNOUNCE,
    FLAG_COMPRESSED,
    FLAG_FAILED,
    FLAG_REPLY,
    FLAG_REQUEST,
    EnvelopeError,
    topic_id_for,
    topic_of,
)
from .wire.envelope import Header as EnvelopeHeader
from .wire.envelope import unpack as unpack_envelope
from .wire.framing import DEFAULT_MAX_MESSAGE, FINISHED_REMEMBERED, FRAGMENT, FramingError
from .wire.names import Layout, NameMissing, pack_name, split_name

__all__ = [
    "API_VERSION", "Address", "BUGS", "BusPattern", "BusRole", "BusTransport", "Call",
    "CallerRoute", "Cipher", "CipherError", "Codec", "CodecError", "Command", "ConfigError",
    "DEFAULT_MAX_MESSAGE", "DatagramEndpoint", "DatagramTransport", "Direction", "Drop",
    "EnvelopeError", "EnvelopeHeader", "FINISHED_REMEMBERED", "FLAG_ANNOUNCE", "FLAG_COMPRESSED",
    "FLAG_FAILED", "FLAG_REPLY", "FLAG_REQUEST", "FRAGMENT", "FastDatagramEndpoint",
    "FastStreamConnection", "FrameHandler", "Framing", "FramingError", "KeyOptions", "Layout",
    "Link", "LinkDrop", "LinkError", "Monitor", "NameMissing", "NoLink", "OptionError",
    "PARTIAL_COST", "Packet", "PacketLink", "Packetizer", "RUNTIME_VARIABLE", "Reason",
    "ReceiveRoute", "RosgateError", "Route", "SOCKET_SUFFIX", "Sender", "ServerRoute",
    "ServiceConfig", "ServiceFraming", "ServiceRoute", "ServiceSpec", "SocketConnection",
    "SocketListener", "Status", "StreamConnection", "StreamListener", "StreamTransport",
    "TopicConfig", "TopicSpec", "Transform", "TransformError", "TransmitRoute", "Transport",
    "TypeNotFound", "Unauthenticated", "check_ip_address", "declare", "describe_source",
    "hookimpl", "identity_public_key", "ip_source_hosts", "key_source", "load_key", "option",
    "pack_name", "parse_host_port", "qos_profile", "resolve_type", "runtime_dir", "socket_path",
    "split_name", "stop_on_signals", "topic_id_for", "topic_of", "type_hash", "unpack_envelope",
    "wait_for_signal",
]
__version__ = "0.1.0"
