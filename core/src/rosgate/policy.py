"""A server's policy: what each client may ask for, default deny (docs/security.md, "Policy").
Each entry of a client's hello is allowed when one rule of its kind under ``clients.NAME``
matches its server-side name (a glob: ``*`` and ``?`` within a segment, ``**`` across),
direction, type, port, cipher and a topic's QoS; :func:`refusal` gives the sentence both sides
log otherwise.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any

from .config import ActionConfig, BridgeConfig, ClientPolicy, Rule, ServiceConfig, TopicConfig
from .config.kinds import ROS_NAME_MAX
from .config.patterns import matches  # one glob for rules and pattern entries

#: an absolute ROS name: parts of letters, digits and '_', none starting with a digit
_ROS_NAME = re.compile(r"(?:/[A-Za-z_][A-Za-z0-9_]*)+")


#: a name inside an action (``/x/_action/status``): only an ``actions:`` rule grants it
_ACTION_PART = re.compile(r"(^|/)_action(/|$)")


def is_action_part(name: str) -> bool:
    """Whether ``name`` (a name or a rule's glob) names something inside an action."""
    return _ACTION_PART.search(name) is not None


def advice(cfg: BridgeConfig) -> list[str]:
    """What ``check`` and ``run`` say of a server's rules that do not do what they seem to: a
    topic or service rule naming a part of an action (only an actions: rule reaches those), a
    topic or service rule that says ``shared`` (it applies to actions)."""
    said = []
    for client, policy in cfg.clients.items():
        for kind, rules in (("topics", policy.topics), ("services", policy.services)):
            for i, rule in enumerate(rules):
                key = f"clients.{client}.{kind}[{i}]"
                if is_action_part(rule.name):
                    said.append(str(cfg.error(
                        f"{key}.name", f"{rule.name} names a part of an action: no {kind[:-1]} "
                        "rule allows it, only an actions: rule for the action does",
                        f"allow the action with an actions: rule, e.g. - {{name: "
                        f"{rule.name.split('/_action')[0] or '/'}, direction: transmit}}")))
                if rule.shared:
                    said.append(str(cfg.error(f"{key}.shared", f"shared applies to actions: "
                                              f"rules, not to {kind}", "remove shared: here")))
    return said


def refusal(policy: ClientPolicy, entry: TopicConfig | ServiceConfig | ActionConfig,
            keyless: set[str]) -> str | None:
    """Why ``entry`` (as the client sent it) is refused, or None when a rule allows it.
    ``keyless`` ciphers (``none``) are allowed only when named. A name that is not an absolute
    ROS name (``~``, ``..``, empty parts: a bare framing's ``remote`` is text) is refused before
    any rule; an action (``transmit``: the client sends goals) is judged by ``actions:``, and
    only an action's own entry reaches the names inside it (``<action>/_action/...``)."""
    return _judge(policy, entry, keyless)[0]


def shared(policy: ClientPolicy, action: ActionConfig, keyless: set[str]) -> bool:
    """Whether a rule that allows ``action`` says ``shared``: the client sees and may cancel
    every goal of it, not only its own (docs/actions.md)."""
    return any(rule.shared for rule in _judge(policy, action, keyless)[1])


def _judge(policy: ClientPolicy, entry: TopicConfig | ServiceConfig | ActionConfig,
           keyless: set[str]) -> tuple[str | None, list[Rule]]:
    """Why ``entry`` is refused (None: allowed), and the rules that allow it."""
    is_topic = isinstance(entry, TopicConfig)
    kind, rules = (("topic", policy.topics) if is_topic else
                   ("action", policy.actions) if isinstance(entry, ActionConfig) else
                   ("service", policy.services))
    name, direction = entry.remote, str(entry.direction)
    what = name if is_topic else f"{kind} {name}"
    if len(name) > ROS_NAME_MAX or not _ROS_NAME.fullmatch(name):
        return (f"{policy.name} may not {direction} {name!r}: it is not a ROS name (parts of "
                "letters, digits and '_' after a single '/', none starting with a digit)"), []
    if not isinstance(entry, ActionConfig) and is_action_part(name):
        return (f"{policy.name} may not {direction} {what}: it is part of an action (only an "
                "actions: entry, allowed by an actions: rule, carries an action)"), []
    ways = [r for r in rules if r.direction in ("both", direction)]
    by_name = [r for r in ways if matches(r.name, name)]
    if not by_name:
        allowed = [r.name for r in ways]
        says = ", ".join(allowed) if allowed else f"no {kind}s it {direction}s"
        return (f"{policy.name} may not {direction} {what} (policy for {policy.name} allows "
                f"{says})"), []
    checks: list[tuple[str, Any, Callable[[Rule], bool], Callable[[Rule], str]]] = [
        ("type", entry.type, lambda r: r.types is None
         or any(matches(t, entry.type) for t in r.types),
         lambda r: f"types {', '.join(r.types or ())}"),
        ("port", entry.port, lambda r: entry.port is None
         or any(low <= entry.port <= high for low, high in r.ports),
         lambda r: "ports " + (", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in r.ports)
                               or "none but the main port")),
        ("cipher", entry.cipher, lambda r: entry.cipher in r.ciphers if r.ciphers is not None
         else entry.cipher not in keyless,
         lambda r: "ciphers " + (", ".join(r.ciphers) if r.ciphers is not None
                                 else "keyed by the session (not none)")),
    ]
    if isinstance(entry, TopicConfig):
        depth, durability = _asked_qos(entry.qos)
        checks += [
            ("depth", depth or "keep_all", lambda r: depth <= r.depth if depth else r.keep_all,
             lambda r: f"depth at most {r.depth}" + (" or keep_all" if r.keep_all else "")),
            ("durability", durability, lambda r: r.durability is None
             or durability in r.durability,
             lambda r: "durability " + ", ".join(r.durability or ())),
        ]
    for label, value, allows, describe in checks:
        if not any(allows(r) for r in by_name):
            rule = by_name[0]
            return (f"{policy.name} may not {direction} {what} with {label} {value} (policy "
                    f"for {policy.name} allows {describe(rule)} for {rule.name})"), []
    allowing = [rule for rule in by_name if all(check[2](rule) for check in checks)]
    if allowing:
        return None, allowing
    return (f"{policy.name} may not {direction} {what} as asked (no rule of policy for "
            f"{policy.name} allows its type, port, cipher and QoS together)"), []


#: names every rule pattern must match to be said to cover everything: short, deep, odd
_ANY_NAME = ("/a", "/a/b", "/_x9/y/z/w/v/u")
_ANY_TYPE = ("std_msgs/msg/String", "x/srv/Y", "nav2_msgs/action/NavigateToPose")


def broad_rules(clients: dict[str, ClientPolicy], file: str) -> list[str]:
    """A warning for each rule that allows every name (``/**``) with any type: the client may
    then publish, call or send goals to anything on the server's graph (its robots' ``cmd_vel``
    too), which a policy is there to prevent."""
    out = []
    for policy in clients.values():
        for kind, rules in (("topics", policy.topics), ("services", policy.services),
                            ("actions", policy.actions)):
            for i, rule in enumerate(rules):
                if all(matches(rule.name, n) for n in _ANY_NAME) and (
                        rule.types is None
                        or any(all(matches(t, x) for x in _ANY_TYPE) for t in rule.types)):
                    where = f"{file}:{rule.line}" if rule.line else file
                    out.append(
                        f"{where}: clients.{policy.name}.{kind}[{i}]: allows every name "
                        f"({rule.name}) with any type, {rule.direction}: {policy.name} may reach "
                        f"every {kind[:-1]} of this server's ROS graph. Name what it needs "
                        f"(e.g. name: /{policy.name}/**) and its types (types: [...])")
    return out


def _asked_qos(spec: int | str | dict) -> tuple[int | None, str]:
    """The depth (None: keep_all) and durability a topic's QoS asks for, as rclpy makes it."""
    from rclpy import qos

    from .rostypes import qos_profile

    profile = qos_profile(spec)
    depth = None if profile.history == qos.HistoryPolicy.KEEP_ALL else int(profile.depth)
    lasting = profile.durability == qos.DurabilityPolicy.TRANSIENT_LOCAL
    return depth, "transient_local" if lasting else "volatile"
