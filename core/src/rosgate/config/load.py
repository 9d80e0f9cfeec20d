"""bringup.yaml: parse, validate, fill defaults; every mistake one ConfigError naming the file, the
line, the key and the fix. Each key is read against its declaration (schema); this module adds what
ties keys together: which keys a role takes, an entry's framing, defaults that follow other keys,
names listed twice. ``*_from_mapping`` run the same checks on entries a client sends."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ..errors import ConfigError
from ..options import show
from . import kinds, schema
from .clients import ClientPolicy
from .entries import (
    MCU_KEYS,
    NO_PLUGIN,
    ActionConfig,
    Direction,
    Framing,
    ServiceConfig,
    TopicConfig,
)
from .kinds import Key, check_keys, key_names, keys, read, require, row_of
from .patterns import is_pattern, name_or_pattern, split
from .schema import BridgeConfig, Defaults, File, Role
from .source import START_FIX, Source, join, parse


def load(path: str | Path) -> BridgeConfig:
    file = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"not UTF-8 text (byte {exc.start}: {exc.reason})", file=file,
                          fix="save the file as UTF-8") from None
    except OSError as exc:
        raise ConfigError(f"cannot read the file: {exc.strerror or exc}", file=file,
                          fix="check the path and its permissions") from None
    return loads(text, file=file, base_dir=Path(path).absolute().parent)


def loads(text: str, file: str = "<string>", base_dir: Path | None = None) -> BridgeConfig:
    data, src = parse(text, file)
    return _bridge_config(data, src, base_dir if base_dir is not None else Path.cwd())


def topic_from_mapping(data: dict, defaults: dict[str, str], where: str, *,
                       index: int | None = None) -> TopicConfig:
    """Validate one topic entry received from a client; `where` becomes the error's file and
    `index` its position in the client's list (error keys read "topics[3].codec")."""
    path = _entry_path("topics", index)
    return _named(_entry(Source(where), data, path, TopicConfig, defaults), where, path)


def service_from_mapping(data: dict, defaults: dict[str, str], where: str, *,
                         index: int | None = None) -> ServiceConfig:
    """Like topic_from_mapping, for a service entry."""
    path = _entry_path("services", index)
    return _named(_entry(Source(where), data, path, ServiceConfig, defaults), where, path)


def action_from_mapping(data: dict, defaults: dict[str, str], where: str, *,
                        index: int | None = None) -> ActionConfig:
    """Like topic_from_mapping, for an action entry."""
    path = _entry_path("actions", index)
    return _named(_entry(Source(where), data, path, ActionConfig, defaults), where, path)


def _named(entry: Any, where: str, path: str) -> Any:
    """An entry a client sent: a name, never a pattern (its patterns are matched on its side)."""
    if entry.pattern:
        raise ConfigError("a pattern: a client sends the names its patterns found", file=where,
                          key=path, fix="run the same rosgate version on both")
    return entry


def action_to_mapping(a: ActionConfig) -> dict:
    return _to_mapping(a, ActionConfig)


def topic_to_mapping(t: TopicConfig) -> dict:
    """As the user would write it, plugin keys only when used (so that a server that predates them
    still reads a client's hello that does not use them); an unset recovery is left out (the far
    side decides it by the QoS too), ``recovery: none`` is said."""
    mapping = _to_mapping(t, TopicConfig)
    if not t.qos_given:  # the far side finds it from the publishers too
        del mapping["qos"]
    if mapping["compression"] == NO_PLUGIN:
        del mapping["compression"]
    for key, options in (("recovery", t.recovery_options), ("compression", t.compression_options)):
        if key in mapping and options:
            mapping[key] = {mapping[key]: dict(options)}
    return mapping


def service_to_mapping(s: ServiceConfig) -> dict:
    mapping = _to_mapping(s, ServiceConfig)
    if s.framing is not Framing.SERIAL_DATAGRAM or s.direction is not Direction.TRANSMIT:
        del mapping["no_answer"]
    return mapping


def _to_mapping(entry: TopicConfig | ServiceConfig | ActionConfig, section: type) -> dict:
    mapping = {}
    for key in key_names(section):
        value = getattr(entry, key)
        # unset optional keys are left out, as a user would; microcontroller keys are only for
        # microcontroller entries (an entry with an envelope refuses them)
        if value is not None and (entry.framing.bare or key not in MCU_KEYS) \
                and key not in _PATTERN_KEYS:
            mapping[key] = dict(value) if isinstance(value, dict) else value
    return mapping


#: what a pattern entry says of the routes it makes, never sent: a far side gets their names
_PATTERN_KEYS = ("deny", "max_routes")


def _entry_path(key: str, index: int | None) -> str:
    return f"{key}[{index if index is not None else '?'}]"


def _top(src: Source, data: dict, key: str) -> Any:
    """A section of the file: its mapping, or {} when absent."""
    return kinds.mapping(Key(src, "", row_of(File, key)), data.get(key))


# --- the file ------------------------------------------------------------------------------------

def _bridge_config(data: Any, src: Source, base_dir: Path) -> BridgeConfig:
    if not isinstance(data, dict):
        raise src.error("", f"expected a mapping with bridge: at the top, got {show(data)}",
                        fix=START_FIX)
    _reject_legacy(src, data)
    check_keys(src, data, "", key_names(File))
    require(src, data, "", File)
    bridge = _top(src, data, "bridge")
    given = read(src, bridge, "bridge", BridgeConfig)
    role = given["role"]
    _check_role(src, data, bridge, role)
    identity, server_key = _identity(src, bridge, given, role, base_dir)
    defaults = {"transport": Defaults.transport, "codec": Defaults.codec,
                "cipher": Defaults.cipher if identity is None else schema.SESSION_CIPHER_DEFAULT,
                **given.get("defaults", {})}
    heartbeat = given.get("heartbeat", BridgeConfig.heartbeat)
    peer_timeout = given.setdefault("peer_timeout", heartbeat * schema.PEER_TIMEOUT_HEARTBEATS)
    if peer_timeout <= heartbeat:
        raise src.error("bridge.peer_timeout", f"{peer_timeout:g} s is not longer than the "
                        f"heartbeat ({heartbeat:g} s): every peer would be declared down between "
                        "two pings",
                        fix=f"e.g. peer_timeout: {heartbeat * schema.PEER_TIMEOUT_HEARTBEATS:g} "
                            "(three heartbeats)")
    low = given.get("reconnect_min", BridgeConfig.reconnect_min)
    high = given.setdefault("reconnect_max", max(low, schema.RECONNECT_MAX_DEFAULT))
    if high < low:
        raise src.error("bridge.reconnect.max", f"max ({high:g} s) is below min ({low:g} s)",
                        fix="make max at least min, e.g. reconnect: {min: 0.1, max: 10}")
    limits = given.get("limits")
    if limits is not None and limits.connections_per_source > limits.connections:
        raise src.error("bridge.limits.connections_per_source",
                        f"{limits.connections_per_source} per source is more than the "
                        f"{limits.connections} connections allowed in total",
                        fix="make connections at least connections_per_source")
    if "allow" in given and role is not Role.PEER:
        raise src.error("bridge.allow", "allow: is for role peer (a client or server "
                        "authenticates its peers by their keys)", fix="remove it")
    if role is Role.PEER:
        given.setdefault("listen", schema.LISTEN_DEFAULT)
    return BridgeConfig(
        file=src.file, **{**given, "defaults": defaults, "identity": identity,
                          "server_key": server_key},
        clients=_clients(src, data, role), plugins=_plugins(src, data),
        topics=_entries(src, data, "topics", defaults),
        services=_entries(src, data, "services", defaults),
        actions=_entries(src, data, "actions", defaults),
        lines=src.lines, base_dir=base_dir)


def _reject_legacy(src: Source, data: dict) -> None:
    for key, value in data.items():
        if isinstance(value, dict) and "ros__parameters" in value:
            raise src.error(key, f"this is the old ros2_socket_bridge format "
                                 f"({key}: ros__parameters:); rosgate uses bridge: + topics: "
                                 "instead",
                            fix="'rosgate convert FILE' (pip install rosgate-convert) writes "
                                "the rosgate files for it; or rewrite it as in "
                                "docs/configuration.md: a bridge: section (name, role: client, "
                                "server: host:port) and one topics: entry per topic (topic, "
                                "type: pkg/msg/Type, direction, port)")


def _check_role(src: Source, data: dict, bridge: dict, role: Role) -> None:
    if role is Role.PEER:
        for key in ("server", "main_line"):
            if key in bridge:
                raise src.error(f"bridge.{key}",
                                f"role peer has no main line, so {key}: does not apply",
                                fix="remove it; a peer sends to peer: (the far host) and binds "
                                    "listen:")
        # peer: is needed by entries on point-to-point links, not by those on a bus: the
        # resolver, which knows which transport is which, requires it
        return
    for key in ("peer", "listen"):
        if key in bridge:
            raise src.error(f"bridge.{key}", f"{key}: is for role peer only",
                            fix=f"remove it; a {role} uses server: only")
    if "server" not in bridge:
        where = ("host:port, the server's main line" if role is Role.CLIENT
                 else "address:port, where to listen for clients")
        raise src.error("bridge.server", "missing required key 'server'",
                        fix=f"add server: {where}")
    if role is Role.SERVER:
        for key in ("topics", "services", "actions"):
            if data.get(key):
                raise src.error(key, f"a server gets its {key} from its clients, so its file has "
                                     f"no {key}:",
                                fix=f"remove {key}: here and list them in each client's file")


_HANDSHAKE = ("identity", "peer_key", "handshake_port")


def _identity(src: Source, bridge: dict, given: dict, role: Role,
              base_dir: Path) -> tuple[bytes | None, bytes | None]:
    """This side's private key and (client) the server's public key (a peer's: the other peer's).
    Client and server refuse to go without them unless ``insecure: true`` says so."""
    if role is Role.PEER:
        if "server_key" in bridge:
            raise src.error("bridge.server_key", "role peer has no server_key:",
                            fix="a peer authenticates with identity:, peer_key: and "
                                "handshake_port: (docs/security.md), or says insecure: true")
        found = [key for key in _HANDSHAKE if key in bridge]
        lacking = [key for key in _HANDSHAKE if key not in bridge]
        for key in ("rekey", "handshake_line"):
            if not found and key in bridge:
                raise src.error(f"bridge.{key}", f"{key}: is for peers with identities",
                                fix="add identity:, peer_key: and handshake_port:, or remove it")
        if found and lacking:
            raise src.error(f"bridge.{found[0]}", "a peer with a handshake needs identity:, "
                            "peer_key: and handshake_port:",
                            fix=f"add {lacking[0]}: {row_of(BridgeConfig, lacking[0]).example}")
    else:
        for key in ("peer_key", "handshake_port", "handshake_line"):
            if key in bridge:
                raise src.error(f"bridge.{key}", f"{key}: is for role peer",
                                fix="a client names server_key:, a server its clients:")
        if role is Role.SERVER and "server_key" in bridge:
            raise src.error("bridge.server_key", "a server has no server_key: it names its "
                            "clients' keys under clients:", fix="remove it")
        if given.get("insecure"):
            for key in ("identity", "server_key"):
                if key in bridge:
                    raise src.error(f"bridge.{key}", f"insecure: true and {key}: contradict "
                                    "each other", fix="remove insecure: true to authenticate (or "
                                                      "the key to run without)")
            return None, None
        if role is Role.CLIENT and "identity" in bridge and "server_key" not in bridge:
            raise src.error("bridge.identity", "a client with an identity needs the server's "
                            "public key too", fix="add server_key: <the server's public key>")
    if "identity" not in bridge:
        # a client or server without identities is refused when it is planned
        # (Resolver.plan), so that this module still reads any file for what else it may say
        return None, None
    from ..identity import IdentityError, load_private  # its cryptography: only with identities

    try:
        identity = load_private(base_dir / given["identity"])
    except IdentityError as exc:
        raise src.error("bridge.identity", str(exc), fix=exc.fix) from None
    wanted = {Role.PEER: "peer_key", Role.CLIENT: "server_key"}.get(role)
    if wanted is None:
        return identity, None
    return identity, kinds.public_key(Key(src, "bridge", row_of(BridgeConfig, wanted)),
                                      given[wanted])


def _clients(src: Source, data: dict, role: Role) -> dict[str, ClientPolicy]:
    """A server's ``clients:``: each client's public key and its policy (default deny)."""
    given = _top(src, data, "clients")
    if given and role is not Role.SERVER:
        raise src.error("clients", "only a server lists clients", fix="remove clients: here")
    policies: dict[str, ClientPolicy] = {}
    seen: dict[bytes, str] = {}
    for name, entry in given.items():
        path = f"clients.{name}"
        if not kinds.BRIDGE_NAME.fullmatch(name):
            raise src.error(path, f"'{name}' is not a valid client name",
                            fix="use the client's bridge.name: letters, digits, '_', '.', '-'")
        policy = kinds.item(src, path, {} if entry is None else entry, ClientPolicy, "a mapping",
                            f"write it as {name}: {{key: <the client's public key>}}", name)
        if policy.key in seen:
            raise src.error(f"{path}.key", f"the same key as clients.{seen[policy.key]}",
                            fix="give every client an identity of its own")
        seen[policy.key] = name
        policies[name] = policy
    return policies


def _plugins(src: Source, data: dict) -> dict[str, dict]:
    given = _top(src, data, "plugins")
    for name, options in given.items():
        if options is not None and not isinstance(options, dict):
            raise src.error(f"plugins.{name}", f"expected a mapping, got {show(options)}",
                            fix=f"write its options as {name}: {{option: value}}")
    return {name: options or {} for name, options in given.items()}


def _entries(src: Source, data: dict, key: str, defaults: dict[str, str]) -> list:
    items = data.get(key)
    if items is None:
        return []
    if not isinstance(items, list):
        raise src.error(key, f"expected a list of entries, got {show(items)}",
                        fix=f"start each entry with '- {key[:-1]}: ' on its own line under {key}:")
    section = {"topics": TopicConfig, "services": ServiceConfig, "actions": ActionConfig}[key]
    # a peer's port: is checked by the resolver: entries on a bus have none
    entries = [_entry(src, item, f"{key}[{i}]", section, defaults) for i, item in enumerate(items)]
    _check_duplicates(src, key, entries)
    return entries


def _check_duplicates(src: Source, key: str, entries: list) -> None:
    name_key = key[:-1]  # "topic" | "service" | "action"
    by_name: dict[tuple[str, str], int] = {}
    by_remote: dict[str, int] = {}
    for j, entry in enumerate(entries):
        name = getattr(entry, name_key)
        first = by_name.setdefault((name, entry.direction), j)
        if first != j:
            raise src.error(f"{key}[{j}].{name_key}",
                            f"{name} ({entry.direction}) is already listed as {key}[{first}] "
                            f"on line {entries[first].line}", fix="remove one of the two entries")
        if entry.direction is Direction.RECEIVE:
            # incoming frames are routed by remote name: two receivers of one name are ambiguous
            first = by_remote.setdefault(entry.remote, j)
            if first != j:
                raise src.error(f"{key}[{j}].remote",
                                f"remote {entry.remote} is already received by {key}[{first}] "
                                f"on line {entries[first].line}",
                                fix=f"give each receive {name_key} its own remote")


# --- entries (file or network) -------------------------------------------------------------------

def _entry(src: Source, data: Any, path: str, section: type, defaults: dict[str, str]) -> Any:
    """A topic, service or action entry: the keys they share, and the rules that tie them."""
    name_key = keys(section)[0].key  # "topic" | "service" | "action"
    if not isinstance(data, dict):
        raise src.error(path, f"expected a mapping ({name_key}:, type:, direction: ...), "
                              f"got {show(data)}",
                        fix=f"write the entry as '- {name_key}: {keys(section)[0].example}' "
                            "with its other keys indented under it")
    written = data.get(name_key)
    if not (isinstance(written, str) and is_pattern(written)):
        _listed(src, data, path, name_key, section)
    given = read(src, data, path, section)
    name = given[name_key]
    framing = given.setdefault("framing", Framing.ROSGATE)
    if is_pattern(name):
        _pattern(src, data, path, name_key, given)
    if framing.bare:  # the name on the wire as written
        given.setdefault("remote", name.removeprefix("/"))
    elif is_pattern(name):
        given.setdefault("remote", name)  # checked by _pattern
    elif "remote" in given:
        given["remote"] = kinds.remote(Key(src, path, row_of(section, "remote")), given["remote"])
    else:
        given["remote"] = name
    for key in ("transport", "codec", "cipher"):
        given.setdefault(key, defaults.get(key, getattr(Defaults, key)))
    if framing.bare and given["cipher"] != "none":
        raise src.error(join(path, "framing"),
                        f"framing {framing} sends the bare payload, so there is no envelope to "
                        f"authenticate; cipher must be none, not '{given['cipher']}'",
                        fix="set cipher: none on this entry, or use framing: rosgate to keep "
                            "the cipher")
    for key in MCU_KEYS:
        if key in data and not framing.bare:
            raise src.error(join(path, key), f"{key} is for microcontroller entries (framing none "
                            "or serial_datagram); this entry has an envelope",
                            fix=f"remove {key}:, or set framing: none (topics) or "
                                "serial_datagram (services)")
    if section is TopicConfig:
        _topic(src, data, path, given)
    elif section is ServiceConfig:
        _service(src, data, path, given)
    return section(**given, **src.entry_lines(path))


def _pattern(src: Source, data: dict, path: str, name_key: str, given: dict[str, Any]) -> None:
    """A pattern entry: envelope framing (a microcontroller's names are fixed), and a remote: that
    keeps the pattern's wildcards."""
    name = given[name_key]
    given.setdefault("type", "")  # found with each name
    # framing none on a bus (zenoh) is ROS's own CDR on ROS names: the resolver, which knows
    # the transport, judges it
    if given["framing"].bare and not (name_key == "topic" and given["framing"] is Framing.NONE):
        raise src.error(join(path, "framing"), f"a pattern ({name}) finds ROS names as they "
                        f"appear; framing {given['framing']} sends a microcontroller's fixed "
                        "names", fix="list each name as an entry of its own, or remove framing:")
    if "remote" not in given:
        return
    remote = given["remote"] = name_or_pattern(Key(src, path, row_of(TopicConfig, "remote")),
                                               given["remote"])
    tail = split(name)[1]
    if not is_pattern(remote) or split(remote)[1] != tail:
        raise src.error(join(path, "remote"), f"remote {remote} does not keep the pattern's "
                        f"wildcards ({tail}): each name found maps by the part before them",
                        fix=f"end remote with {tail}, e.g. remote: /fleet{name}")


def _listed(src: Source, data: dict, path: str, name_key: str, section: type) -> None:
    """A listed name: its type is needed, pattern keys are not."""
    for key in ("deny", "max_routes"):
        if key in data:
            raise src.error(join(path, key), f"{key} is for pattern entries ({name_key}: "
                            f"/robot1/**); {data[name_key]} is one name",
                            fix=f"remove {key}:, or make {name_key}: a pattern")
    if "type" not in data:
        raise src.error(join(path, "type"), f"missing required key 'type' (only a pattern "
                        f"entry, such as {name_key}: /robot1/**, takes it from the graph)",
                        fix=f"add type: {row_of(section, 'type').example}")


def _topic(src: Source, data: dict, path: str, given: dict[str, Any]) -> None:
    framing = given["framing"]
    if framing is Framing.SERIAL_DATAGRAM:
        raise src.error(join(path, "framing"), "framing serial_datagram is for services (request "
                                               "and answer to a microcontroller), not topics",
                        fix="use framing: none for bare payloads on a datagram link, "
                            "or leave framing: out")
    for key in ("recovery", "compression"):  # a plugin's name and the entry's options for it
        unset = None if key == "recovery" else NO_PLUGIN  # recovery: by the QoS
        given[key], given[f"{key}_options"] = given.get(key, (unset, {}))
        if framing.bare and key in data and data[key] != NO_PLUGIN:
            raise src.error(join(path, key), f"{key} needs the envelope (framing: rosgate): "
                            f"with framing {framing} a datagram is the bare payload",
                            fix=f"remove {key}:, or use framing: rosgate")
    given["qos_given"] = "qos" in data


def _service(src: Source, data: dict, path: str, given: dict[str, Any]) -> None:
    framing = given["framing"]
    if framing is Framing.NONE:
        raise src.error(join(path, "framing"), "framing none is for topics: a service call needs "
                                               "its answer matched to it",
                        fix="leave framing: out (rosgate), or use framing: serial_datagram with a "
                            "microcontroller")
    if "no_answer" in data and (framing is not Framing.SERIAL_DATAGRAM
                                or given["direction"] is not Direction.TRANSMIT):
        raise src.error(join(path, "no_answer"), "no_answer is for calls this bridge makes to a "
                        "microcontroller (direction: transmit, framing: serial_datagram)",
                        fix="remove no_answer: from this entry")
