"""The zenoh transport: options passed to zenoh, keys as zenoh checks them, and the opening of
a bus session (:mod:`.session`) in the dialect the options speak."""


from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import zenoh
import zenoh.ext
from rosgate_fleet import FleetTransport
from rosgate_fleet import check_key as check_chunks

from rosgate import LinkError, OptionError, Unauthenticated, option

from .session import ZenohSession, zenoh_message
from .tls import zenoh_tls

log = logging.getLogger("rosgate.zenoh")

OWN_OPTIONS = ("prefix", "namespace", "speak", "domain", "tls", "insecure")
_ZENOH = "zenoh's own, passed through (see zenoh's DEFAULT_CONFIG.json5)"
_FIX = "see zenoh's DEFAULT_CONFIG.json5 for the options and their forms"
_TLS_FIX = ("set tls: <folder> (certificates made by 'rosgate certs'), connect to tls/<host>:"
            "<port>, and run the router with --tls (docs/fleets.md, Only the fleet)")
_INSECURE_FIX = ("remove plugins.zenoh.insecure; set up TLS (tls: <folder>, docs/fleets.md), or, "
                 "on a network you trust entirely, say bridge.insecure: true with a comment why")


def zenoh_config(options: Mapping[str, Any]) -> zenoh.Config:
    """The zenoh part of the options as a ``zenoh.Config``; :class:`OptionError` naming the
    option (its dotted path) for anything zenoh refuses."""
    given = {k: v for k, v in options.items() if k not in OWN_OPTIONS and v is not None}
    for key in ("connect", "listen"):
        if isinstance(given.get(key), list):
            given[key] = {"endpoints": given[key]}
    scouting = given.setdefault("scouting", {})
    if isinstance(scouting, dict):
        multicast = scouting.setdefault("multicast", {})
        if isinstance(multicast, dict):
            multicast.setdefault("enabled", False)
    if options.get("speak") in ("ros2dds", "rmw_zenoh"):  # caches order samples by timestamp
        given.setdefault("timestamping", {"enabled": True})
    config = zenoh.Config()
    for key, value in given.items():
        _insert(config, key, value)
    return config


def _insert(config: zenoh.Config, path: str, value: Any) -> None:
    try:
        config.insert_json5(path, json.dumps(value))
    except zenoh.ZError as exc:
        if isinstance(value, dict) and value:  # name the option inside that is wrong
            for key, inner in value.items():
                _insert(config, f"{path}/{key}", inner)
        message = zenoh_message(exc)
        if message == "unknown option":
            parent, _, last = path.rpartition("/")
            message = f"unknown zenoh option '{last}'" + (f" under {parent.replace('/', '.')}"
                                                          if parent else "")
        raise OptionError(path.replace("/", "."), message, _FIX) from None
    except (TypeError, ValueError) as exc:  # a value json cannot write: YAML gave something odd
        raise OptionError(path.replace("/", "."), f"cannot be passed to zenoh: {exc}",
                          _FIX) from None


def _json(config: zenoh.Config, path: str) -> Any:
    return json.loads(config.get_json(path))


def _mutual_tls(folder: str | None, tls: Any) -> bool:
    """rosgate's certificates, or zenoh's own TLS settings asking the far side for a
    certificate that a CA signed."""
    return folder is not None or isinstance(tls, dict) and tls.get("enable_mtls") is True and \
        bool(tls.get("root_ca_certificate") or tls.get("root_ca_certificate_base64"))


def check_key(key: str) -> str:
    """A key as rosgate and zenoh both take it; ``ValueError`` saying why not."""
    check_chunks(key)
    try:
        zenoh.KeyExpr(key)
    except zenoh.ZError as exc:
        raise ValueError(f"{key!r} is not a zenoh key expression: {zenoh_message(exc)}") from None
    return key


class ZenohTransport(FleetTransport):
    name = "zenoh"

    @dataclass(frozen=True)
    class Options:
        """rosgate's two options, then zenoh's own configuration sections, passed through."""

        prefix: str = option("rosgate", "first part of rosgate's keys (<prefix>/<bridge>/<topic>) "
                             "and liveliness tokens; the same across a fleet")
        namespace: str = option("/", "framing: none keys are <namespace>/<ROS name>, as "
                                "zenoh-bridge-ros2dds' namespace (shadows zenoh's own)")
        speak: Literal["rosgate", "ros2dds", "rmw_zenoh"] = option(
            "rosgate", "ros2dds: framing-none topics and cipher-none services (codec cdr) are "
            "announced, cached and called as zenoh-bridge-ros2dds does; rmw_zenoh: the same "
            "entries are keyed, attached and announced as rmw_zenoh nodes do; rosgate: "
            "rosgate's own")
        domain: int | None = option(
            None, "speak: rmw_zenoh: the ROS domain id of the rmw_zenoh nodes (the first part "
            "of their keys and tokens); default: this bridge's own (ROS_DOMAIN_ID)", minimum=0)
        tls: str | None = option(
            None, "a folder of certificates made by 'rosgate certs': mutual TLS with the "
            "fleet's CA, presenting <bridge name>.pem (endpoints tls/<host>:<port>); relative to "
            "this file", relative=True)
        insecure: bool | None = option(
            None, "not an option here: a file has one insecure key, bridge.insecure (refused "
            "with that fix)")
        mode: Literal["peer", "client", "router"] = option(
            "peer", "zenoh's mode: peer opens without a router, client needs one at start")
        connect: dict[str, Any] | list[str] | None = option(
            None, "zenoh's connect: {endpoints: [...], retry: {...}}, or the endpoints alone")
        listen: dict[str, Any] | list[str] | None = option(
            None, "zenoh's listen: {endpoints: [...]}, or the endpoints alone")
        scouting: dict[str, Any] | None = option(
            None, "zenoh's scouting; multicast is off unless enabled here")
        transport: dict[str, Any] | None = option(
            None, "zenoh's transport: link (tls, tx.lease...), unicast, shared_memory...")
        id: str | None = option(None, _ZENOH)
        metadata: dict[str, Any] | None = option(None, _ZENOH)
        open: dict[str, Any] | None = option(None, _ZENOH)
        timestamping: dict[str, Any] | None = option(None, _ZENOH)
        queries_default_timeout: int | None = option(None, _ZENOH + "; milliseconds")
        routing: dict[str, Any] | None = option(None, _ZENOH)
        aggregation: dict[str, Any] | None = option(None, _ZENOH)
        qos: dict[str, Any] | None = option(None, _ZENOH)
        adminspace: dict[str, Any] | None = option(None, _ZENOH)
        downsampling: list[Any] | None = option(None, _ZENOH)
        low_pass_filter: list[Any] | None = option(None, _ZENOH)
        access_control: dict[str, Any] | None = option(None, _ZENOH)

        def __post_init__(self) -> None:
            if self.insecure is not None:
                raise OptionError("insecure", "a file has one insecure key, bridge.insecure, "
                                  "for every entry on every link", _INSECURE_FIX)
            try:
                check_key(self.prefix)
            except ValueError as exc:
                raise OptionError("prefix", str(exc), "e.g. prefix: fleet") from None
            if self.namespace.strip("/"):
                try:
                    check_key(self.namespace.strip("/"))
                except ValueError as exc:
                    raise OptionError("namespace", str(exc), "e.g. namespace: /bot1 (as "
                                      "zenoh-bridge-ros2dds writes it)") from None
            zenoh_config(dataclasses.asdict(self))  # zenoh refuses now: `rosgate check` shows it

    options: Options

    def __init__(self, options: Any):
        super().__init__(options)
        self.prefix = self.options.prefix
        self.namespace = self.options.namespace.strip("/")
        # the fleet code works with the core's routes: imported for a bridge, not for a router
        from .fleet import Fleets

        self.templates = Fleets(self)
        if self.options.speak == "ros2dds":
            from .dialect import Ros2dds

            self.dialect = Ros2dds()
        elif self.options.speak == "rmw_zenoh":
            from .rmw_dialect import RmwZenoh

            self.dialect = RmwZenoh()

    def check_key(self, key: str) -> str:
        return check_key(key)

    def default_key(self, bridge: str, ros_name: str, bare: bool) -> str:
        """Bare frames: ``<namespace>/<ROS name>``, as zenoh-bridge-ros2dds keys them."""
        key = super().default_key(bridge, ros_name, bare)
        return f"{self.namespace}/{key}" if bare and self.namespace else key

    def unauthenticated(self) -> Unauthenticated | None:
        """Open unless zenoh's mutual TLS guards every link this session has or can get: a CA
        (``tls:``, or zenoh's own ``transport.link.tls`` with ``enable_mtls``), only ``tls/``
        endpoints to connect and to listen on (a peer or a router listens on zenoh's default
        ``tcp/[::]`` unless ``listen:`` says otherwise), and no multicast scouting, which
        joins whoever answers."""
        config, mode = zenoh_config(dataclasses.asdict(self.options)), self.options.mode
        if not _mutual_tls(self.options.tls, _json(config, "transport/link/tls")):
            return Unauthenticated("tls", "no mutual TLS: zenoh takes a session from anyone who "
                                   "reaches this bridge or its router", _TLS_FIX)
        written = {"connect": self.options.connect, "listen": self.options.listen}
        for section, given in written.items():
            endpoints = _json(config, f"{section}/endpoints")
            if isinstance(endpoints, dict):  # zenoh's defaults, or the file's, per mode
                endpoints = endpoints.get(mode)
            for endpoint in endpoints or ():
                if str(endpoint).startswith("tls/"):
                    continue
                if given is None:  # zenoh's own default listener
                    return Unauthenticated(
                        "mode", f"mode: {mode} listens on zenoh's default {endpoint} (every "
                        "interface) without TLS, where no router's access control sees who "
                        "connects", "use mode: client (through the router, which checks what "
                        "each robot may do), or say where it listens: listen: [tls/<host>:"
                        "<port>], or listen: [] for nowhere")
                return Unauthenticated(
                    section, f"{section} endpoint {endpoint} is not TLS: whoever answers or "
                    "dials there is not authenticated", f"write it tls/"
                    f"{str(endpoint).partition('/')[2]} (only tls/ endpoints are mutual TLS)")
        if _json(config, "scouting/multicast/enabled") is not False:
            return Unauthenticated("scouting", "multicast scouting joins whoever answers on the "
                                   "local network", "remove scouting.multicast.enabled: connect: "
                                   "names the router")
        return None

    def open(self, name: str) -> ZenohSession:
        config = zenoh_config(dataclasses.asdict(self.options))
        if self.options.tls is not None:
            try:
                config.insert_json5("transport/link/tls",
                                    json.dumps(zenoh_tls(self.options.tls, name)))
            except FileNotFoundError as exc:
                raise LinkError(f"zenoh: no certificate {exc} for {name!r}",
                                f"make it with 'rosgate certs --out {self.options.tls} "
                                f"{name}' (docs/fleets.md)") from None
        try:
            session = zenoh.open(config)
        except zenoh.ZError as exc:
            raise LinkError(f"zenoh: cannot open a session: {zenoh_message(exc)}",
                            "check plugins.zenoh: with mode: client a router must answer at one "
                            "of connect.endpoints; mode: peer opens without one") from None
        info = session.info
        log.info("%s: zenoh session %s (%s), routers %s", name, session.zid(), self.options.mode,
                 [str(z) for z in info.routers_zid()] or "none")
        if self.options.speak == "rmw_zenoh":
            from .rmw_dialect import RmwSession

            return RmwSession(session)
        return ZenohSession(session)
