"""bringup.yaml: its keys declared once (``schema``), read with every mistake located at its file,
line and key (``load``), and its reference generated for docs/configuration.md (``docs``)."""

from .kinds import PRIORITIES, QOS_PROFILES, parse_bandwidth
from .load import (
    load,
    loads,
    service_from_mapping,
    service_to_mapping,
    topic_from_mapping,
    topic_to_mapping,
)
from .schema import (
    CIPHER_DEFAULT,
    CODEC_DEFAULT,
    MAX_DELAY_DEFAULT,
    RECOVERY_OVERHEAD_DEFAULT,
    TRANSPORT_DEFAULT,
    BridgeConfig,
    ClientPolicy,
    Compression,
    Direction,
    Framing,
    Limits,
    LinkConfig,
    Recovery,
    Role,
    Rule,
    ServiceConfig,
    TopicConfig,
)

__all__ = [
    "CIPHER_DEFAULT", "CODEC_DEFAULT", "MAX_DELAY_DEFAULT", "PRIORITIES", "QOS_PROFILES",
    "RECOVERY_OVERHEAD_DEFAULT", "TRANSPORT_DEFAULT", "BridgeConfig", "ClientPolicy",
    "Compression", "Direction", "Framing", "LinkConfig", "Limits", "Recovery", "Role", "Rule",
    "ServiceConfig", "TopicConfig", "load", "loads", "parse_bandwidth", "service_from_mapping",
    "service_to_mapping", "topic_from_mapping", "topic_to_mapping",
]
