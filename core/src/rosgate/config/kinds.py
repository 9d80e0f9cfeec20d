"""Reading bringup.yaml against its declarations: a section's keys and each value by its kind,
every mistake a ConfigError located at its key. A declared type's value is read as a plugin's
option is (rosgate.options); a field names other kinds with ``option(parse=...)``, whose docstring
is its "values" column in docs/configuration.md."""

from __future__ import annotations

import ipaddress
import re
from dataclasses import dataclass, replace
from functools import cache
from typing import Any

from ..errors import ConfigError
from ..options import Declared, check, did_you_mean, fields_of, missing, show, unknown
from .source import Source, join

QOS_DEPTH_MAX = 100_000  # far past any real queue; rclpy fails on depths past 64 bits
ROS_NAME_MAX = 200  # characters: rclpy refuses topic names past 247, service names sooner
# rclpy.qos.qos_profile_<name> for each
QOS_PROFILES = ("default", "system_default", "sensor_data", "services_default", "parameters",
                "best_available")
QOS_POLICIES = {
    "reliability": ("reliable", "best_effort"),
    "durability": ("volatile", "transient_local"),
    "history": ("keep_last", "keep_all"),
}
QOS_KEYS = (*QOS_POLICIES, "depth")
#: a topic's priority (zenoh's numbering): 1 the most urgent, 7 the least; default data (5). On a
#: bus zenoh's own; on datagram and stream links the classes of the link's scheduler
PRIORITIES = {"real_time": 1, "interactive_high": 2, "interactive_low": 3, "data_high": 4,
              "data": 5, "data_low": 6, "background": 7}

_NAME_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_PLACEHOLDER = re.compile(r"\{[^{}/]*\}")
# a bus key as written for remote: chunks without wildcards or a leading slash (bus.py says more)
_BUS_KEY = re.compile(r"[^/*$?#\s]+(?:/[^/*$?#\s]+)*")
# pkg/Type or pkg/<kind>/Type; ROS package names are lower case, interface names CamelCase
_INTERFACE = re.compile(r"([a-z][a-z0-9_]*)/(?:([a-z]+)/)?([A-Z][A-Za-z0-9]*)")
_BANDWIDTH = re.compile(r"(\d+(?:\.\d*)?|\.\d+)\s*([kmg]?)(?:bit)?(?:/s)?", re.IGNORECASE)
_BANDWIDTH_UNITS = {"": 1, "k": 1e3, "m": 1e6, "g": 1e9}


@dataclass(frozen=True)
class Key:
    """One key being read: where (its section's path in the file), and its declaration."""

    src: Source
    section: str
    row: Declared

    @property
    def name(self) -> str:
        return self.row.key.rpartition(".")[2]

    @property
    def path(self) -> str:
        return join(self.section, self.name)

    @property
    def example(self) -> str:
        return self.row.example or "<value>"

    def error(self, message: str, fix: str | None = None) -> ConfigError:
        return self.src.error(self.path, message, fix=fix or self.row.fix())


# -- a section ----------------------------------------------------------------------------------

@cache
def keys(section: type) -> tuple[Declared, ...]:
    """The keys ``section`` declares, in the order the file's reference lists them."""
    return tuple(row for row in fields_of(section) if row.doc)


def row_of(section: type, key: str) -> Declared:
    return next(row for row in keys(section) if row.key == key)


def key_names(section: type, under: str = "") -> tuple[str, ...]:
    """The valid keys of ``section`` (or of its sub-mapping ``under``: "reconnect")."""
    prefix = f"{under}." if under else ""
    found = [row.key[len(prefix):].partition(".")[0] for row in keys(section)
             if row.key.startswith(prefix)]
    return tuple(dict.fromkeys(found))


def read(src: Source, data: Any, path: str, section: type) -> dict[str, Any]:
    """The written keys of ``data`` (the mapping at ``path``) by field name, as fields hold them."""
    check_keys(src, data, path, key_names(section))
    require(src, data, path, section)
    values: dict[str, Any] = {}
    for row in keys(section):
        under, _, name = row.key.rpartition(".")
        table = data
        if under:
            table = data.get(under)
            if table is None:  # absent or written empty
                continue
            if not isinstance(table, dict):  # the fix shows its first three keys
                rows = [r for r in keys(section) if r.key.startswith(f"{under}.")][:3]
                example = ", ".join(f"{r.key.rpartition('.')[2]}: {r.example}" for r in rows)
                parent = Declared(under, dict, None, example=f"{{{example}}}", key=under)
                mapping(Key(src, path, parent), table)  # raises, saying what to write
            check_keys(src, table, join(path, under), key_names(section, under))
        if name in table:
            key = Key(src, join(path, under) if under else path, row)
            values[row.name] = (row.parse or plain)(key, table[name])
    return values


def item(src: Source, path: str, value: Any, section: type, what: str, fix: str,
         *args: Any) -> Any:
    """``section`` made of ``value``, one of a collection's mappings (a rule, a link, a client)."""
    if not isinstance(value, dict):
        raise src.error(path, f"expected {what}, got {show(value)}", fix=fix)
    return section(*args, **read(src, value, path, section), line=src.lines.get(path, 0))


def check_keys(src: Source, data: dict, path: str, valid: tuple[str, ...]) -> None:
    for key in data:
        if key not in valid:
            raise src.error(join(path, key), *unknown(key, valid))


def require(src: Source, data: dict, path: str, section: type) -> None:
    for row in keys(section):
        if row.required and row.key not in data:
            raise src.error(join(path, row.key), *missing(row, f"{path}:" if path else ""))


# -- the plain kinds -----------------------------------------------------------------------------

def text(key: Key, value: Any) -> str:
    """text"""
    if value is not None and not isinstance(value, str) and key.path in key.src.texts:
        # keep what was written: YAML 1.1 reads 10:11:22:33:44:55 (a Bluetooth address) as a number
        value = key.src.texts[key.path]
    if not isinstance(value, str) or not value.strip():
        raise key.error(f"expected a non-empty string, got {show(value)}")
    return value


def plain(key: Key, value: Any) -> Any:
    """A value its declared type says how to read (null is none: the key is left out)."""
    arms = getattr(key.row.type, "__args__", (key.row.type,))
    row = replace(key.row, type=next(arm for arm in arms if arm is not type(None)))
    if row.type is str and row.choices is None:
        return text(key, value)
    try:
        return check(row, value)
    except ValueError as exc:
        raise key.error(*exc.args) from None


# -- the kinds a field names with option(parse=...) ---------------------------------------------

def ros_name(key: Key, value: Any) -> str:
    """a ROS name (`/robot1/scan`); `{placeholders}` in fleet entries"""
    name = text(key, value)
    if name.startswith("~"):
        raise key.error(f"private names (~) are not supported: '{name}'",
                        fix=f"write the full name, e.g. {key.name}: {key.example}")
    if len(name) > ROS_NAME_MAX:
        raise key.error(f"a name of {len(name)} characters is longer than ROS takes "
                        f"({ROS_NAME_MAX})", fix=f"use a shorter name, e.g. {key.name}: "
                                                  f"{key.example}")
    tokens = name.removeprefix("/").split("/")
    if not all(_NAME_TOKEN.fullmatch(token) or _PLACEHOLDER.fullmatch(token) for token in tokens):
        raise key.error(f"'{name}' is not a valid ROS name",
                        fix="use letters, digits and '_' in parts separated by single '/', no part "
                            f"starting with a digit, e.g. {key.name}: {key.example}")
    return "/" + "/".join(tokens)  # relative names are taken from the root namespace


def remote(key: Key, value: Any) -> str:
    """a ROS name, or a bus key (`fleet/robot-1/scan`); with bare framing, the name as written"""
    name = text(key, value)
    tokens = name.removeprefix("/").split("/")
    if all(_NAME_TOKEN.fullmatch(t) or _PLACEHOLDER.fullmatch(t) for t in tokens):
        return "/" + "/".join(tokens)
    # only the resolver knows which transport the entry is on, and says so when a key is given to
    # a point-to-point link
    return name if _BUS_KEY.fullmatch(name) else ros_name(key, name)  # ros_name raises, saying why


def interface(kind: str) -> Any:
    """The parse function of a ``type:`` key of entries of ``kind`` (msg, srv, action)."""
    what = {"msg": "a topic", "srv": "a service", "action": "an action"}[kind]

    def parse(key: Key, value: Any) -> str:
        name = text(key, value)
        match = _INTERFACE.fullmatch(name)
        if match is None:
            raise key.error(f"'{name}' is not an interface type name",
                            fix=f"write it as package/{kind}/Type, e.g. type: {key.example}")
        package, middle, last = match.groups()
        if middle not in (None, kind):
            raise key.error(f"'{name}' is a '{middle}' type, but {what} needs package/{kind}/Type")
        return f"{package}/{kind}/{last}"

    parse.__doc__ = f"`pkg/{kind}/Type` (`pkg/Type` is read so too)"
    return parse


def qos(key: Key, value: Any) -> int | str | dict:
    """a depth; a profile: `sensor_data`, `system_default`, `default`, `services_default`,
    `parameters`, `best_available`; or `{reliability: reliable | best_effort, durability: volatile
    | transient_local, history: keep_last | keep_all, depth}`"""
    fix = ("e.g. qos: 10, qos: sensor_data or qos: {reliability: reliable, depth: 10}; "
           f"profiles: {', '.join(QOS_PROFILES)}")
    if isinstance(value, str):
        if value.isascii() and value.isdigit():  # legacy files wrote depths as strings: '10'
            value = int(value)
        else:
            name = value.removeprefix("qos_profile_")  # legacy rclpy spelling
            if name in QOS_PROFILES:
                return name
            raise key.error(f"unknown QoS profile '{value}'"
                            f"{did_you_mean(name, QOS_PROFILES)[1]}", fix=fix)
    if isinstance(value, int) and not isinstance(value, bool):
        return _depth(key.src, key.section, key.name, value)
    if not isinstance(value, dict):
        raise key.error("expected a depth (integer >= 1), a profile name or a mapping "
                        f"{{{', '.join(QOS_KEYS)}}}, got {show(value)}", fix=fix)
    check_keys(key.src, value, key.path, QOS_KEYS)
    policies: dict[str, Any] = {}
    for name, choices in QOS_POLICIES.items():
        if name in value:
            row = Declared(name, str, choices=choices, key=name)
            policies[name] = plain(Key(key.src, key.path, row), value[name])
    if "depth" in value:
        policies["depth"] = _depth(key.src, key.path, "depth", value["depth"])
    return policies


def _depth(src: Source, section: str, name: str, value: Any) -> int:
    """A QoS depth (`qos: 10`, `qos: {depth: 10}`), no deeper than a subscriber can hold."""
    row = Declared(name, int, doc="the QoS depth", minimum=1, maximum=QOS_DEPTH_MAX,
                   unit="messages", example="10", key=name)
    return plain(Key(src, section, row), value)


def plugin_choice(key: Key, value: Any) -> tuple[str, dict[str, Any]]:
    """`none`, a plugin's name, or `{name: {option: value}}`: the entry's own options over the
    plugin's `plugins:` table (the resolver checks them against the plugin's declaration)"""
    fix = f"write it as {key.name}: {key.row.example}"
    if isinstance(value, dict):
        if len(value) != 1:
            raise key.error(f"expected one {key.name} plugin with its options, got "
                            f"{len(value)} names", fix=fix)
        ((name, options),) = value.items()
        options = {} if options is None else options
        if not isinstance(name, str) or not isinstance(options, dict):
            raise key.error(f"expected a name and a mapping of its options, got "
                            f"{show(name)}: {show(options)}", fix=fix)
        return name, options
    if not isinstance(value, str) or not _NAME_TOKEN.fullmatch(value):
        raise key.error(f"expected a plugin's name, got {show(value)}", fix=fix)
    return value, {}


def priority(key: Key, value: Any) -> int:
    """`real_time` (1), `interactive_high`, `interactive_low`, `data_high`, `data`, `data_low`,
    `background` (7), or 1..7"""
    if isinstance(value, str) and value in PRIORITIES:
        return PRIORITIES[value]
    if isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= 7:
        return value
    raise key.error(f"expected a priority, 1 (real_time) to 7 (background), got {show(value)}"
                    f"{did_you_mean(str(value), tuple(PRIORITIES))[1]}",
                    fix=f"one of {', '.join(PRIORITIES)} (or 1..7)")


def parse_bandwidth(value: Any) -> float:
    """Bits per second from ``20mbit``, ``20 Mbit/s``, ``500kbit``, ``1.5gbit``, ``20M`` or a plain
    number; ValueError for anything else. Bytes are refused, and so is ``mbps``, which tc reads
    as megabytes and most people as megabits."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        bits = float(value)
    else:
        match = _BANDWIDTH.fullmatch(value.strip()) if isinstance(value, str) else None
        if match is None:
            raise ValueError(f"expected a bandwidth in bits per second, got {show(value)}")
        bits = float(match.group(1)) * _BANDWIDTH_UNITS[match.group(2).lower()]
    if not bits > 0:
        raise ValueError(f"a bandwidth must be > 0, got {show(value)}")
    return bits


def bandwidth(key: Key, value: Any) -> float:
    """bits per second: `20mbit`, `500kbit`, `1.5gbit`, `20000000`"""
    try:
        return parse_bandwidth(value)
    except ValueError as exc:
        raise key.error(str(exc), fix="bits per second: 20mbit, 500kbit, 1.5gbit or 20000000 "
                                      "(2.5 megabytes per second is 20mbit)") from None


def networks(key: Key, value: Any) -> tuple[Any, ...]:
    """IP addresses or networks: `[192.168.0.20, 10.1.0.0/24]`"""
    found = []
    for item in value if isinstance(value, list) else [value]:
        try:
            found.append(ipaddress.ip_network(str(item), strict=False))
        except ValueError:
            raise key.error(f"{item!r} is not an IP address or network") from None
    return tuple(found)


def port_ranges(key: Key, value: Any) -> tuple[tuple[int, int], ...]:
    """ports and ranges: `[12001, 12010-12019]`"""
    ranges = []
    for item in value if isinstance(value, list) else [value]:
        low, _, high = str(item).partition("-")
        try:
            first, last = int(low), int(high or low)
        except ValueError:
            first, last = 0, -1
        if isinstance(item, bool) or not 1 <= first <= last <= 65535:
            raise key.error(f"{item!r} is not a port or a range of ports")
        ranges.append((first, last))
    return tuple(ranges)


def names(key: Key, value: Any) -> tuple[str, ...]:
    """a list of names (globs)"""
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise key.error(f"expected a list of names, got {show(value)}")
    return tuple(value)


def durabilities(key: Key, value: Any) -> tuple[str, ...]:
    """a list of durabilities: `volatile`, `transient_local`"""
    one = replace(key.row, type=str, choices=QOS_POLICIES["durability"], example=None)
    return tuple(plain(Key(key.src, key.section, one), name) for name in names(key, value))


def mapping(key: Key, value: Any) -> dict:
    """a mapping"""
    if value is None:  # written empty
        return {}
    if not isinstance(value, dict):
        raise key.error(f"expected a mapping, got {show(value)}",
                        fix=f"write it as {key.name}: {key.example}")
    return value


def public_key(key: Key, value: Any) -> bytes:
    """a public key, base64 (44 characters, printed by `rosgate keygen identity`)"""
    from ..identity import IdentityError, decode_public

    try:
        return decode_public(text(key, value))
    except IdentityError as exc:
        raise key.error(f"the {key.name} {exc}", fix=exc.fix) from None


def bridge_name(key: Key, value: Any) -> str:
    """letters, digits, `_`, `.` and `-`"""
    name = text(key, value)
    if not BRIDGE_NAME.fullmatch(name):
        raise key.error(f"'{name}' is not a valid bridge name",
                        fix=f"use only letters, digits, '_', '.' and '-', e.g. name: {key.example}")
    return name


BRIDGE_NAME = re.compile(r"[A-Za-z0-9_.-]+")
