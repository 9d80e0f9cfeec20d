"""bringup.yaml: its keys declared once (``schema``: the file and ``bridge:``; ``entries``: a
topic's, service's, action's; ``clients``), read with every mistake located at its file, line
and key (``load``); docs/configuration.md's reference is generated from the schema by the
``rosgate_docgen`` development tool (``tools/docgen``)."""

from .clients import ClientPolicy, Rule
from .entries import (
    NO_PLUGIN,
    TIMEOUT_MAX,
    ActionConfig,
    Direction,
    Framing,
    ServiceConfig,
    TopicConfig,
)
from .kinds import PRIORITIES, QOS_POLICIES, QOS_PROFILES, parse_bandwidth
from .load import (
    action_from_mapping,
    action_to_mapping,
    load,
    loads,
    service_from_mapping,
    service_to_mapping,
    topic_from_mapping,
    topic_to_mapping,
)
from .schema import MAX_DELAY_DEFAULT, BridgeConfig, Limits, LinkConfig, Role

__all__ = [
    "MAX_DELAY_DEFAULT", "NO_PLUGIN", "PRIORITIES", "QOS_POLICIES", "QOS_PROFILES", "TIMEOUT_MAX",
    "ActionConfig", "BridgeConfig", "ClientPolicy", "Direction", "Framing", "LinkConfig", "Limits",
    "Role", "Rule", "ServiceConfig", "TopicConfig", "action_from_mapping", "action_to_mapping",
    "load", "loads", "parse_bandwidth", "service_from_mapping", "service_to_mapping",
    "topic_from_mapping", "topic_to_mapping",
]
