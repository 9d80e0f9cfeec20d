"""``rosgate router``: a zenoh router for bridges to meet at, until SIGINT or SIGTERM.

Bridges in ``mode: client`` need one at start; peers attach when one comes. ``--listen`` takes
zenoh endpoints (``tcp/0.0.0.0:7447``, repeatable); ``--config`` takes zenoh's own JSON5 file, as
``zenohd -c`` does. Without ``--config`` multicast scouting is off, as for the bridges.
"""

from __future__ import annotations

import argparse
import json
import logging
from typing import Any

import zenoh

from rosgate import Command, LinkError, stop_on_signals, wait_for_signal

from .session import ZenohSession, zenoh_message
from .tls import access_control, make, zenoh_tls
from .transport import ZenohTransport

LISTEN = "tcp/0.0.0.0:7447"
LISTEN_TLS = "tls/0.0.0.0:7447"
#: the zenoh plugin's default prefix: a bridge's liveliness token unless its file sets prefix:
TOKENS = ZenohTransport.Options.prefix

log = logging.getLogger("rosgate")


def arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                        help=f"where to listen, repeatable (default {LISTEN}, {LISTEN_TLS} "
                             "with --tls)")
    parser.add_argument("--config", metavar="FILE",
                        help="zenoh's own configuration file (JSON5, as for zenohd -c)")
    parser.add_argument("--tls", metavar="DIR",
                        help="mutual TLS with the certificates 'rosgate certs' made in DIR: "
                             "only bridges the fleet's CA signed connect")
    parser.add_argument("--name", default="router",
                        help="the router's certificate in DIR (default router)")
    parser.add_argument("--robot", action="append", default=[], metavar="NAME",
                        help="with --tls: a robot (its certificate's name) that may send and "
                             "take only on PREFIX/NAME/**, its token PREFIX/NAME/@alive or "
                             f"{TOKENS}/NAME/@alive; repeatable. With a --robot or --base "
                             "every other session is denied everything")
    parser.add_argument("--base", action="append", default=[], metavar="NAME",
                        help="with --tls: a base that may send and take on every key; repeatable")
    parser.add_argument("--prefix", default="fleet",
                        help="the first part of the robots' keys (default fleet)")


def open_router(listen: list[str], config_file: str | None,
                extra: dict[str, Any] | None = None) -> ZenohSession:
    """A zenoh session in router mode; :class:`rosgate.LinkError` when zenoh refuses."""
    try:
        config = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
        config.insert_json5("mode", json.dumps("router"))
        if listen:
            config.insert_json5("listen/endpoints", json.dumps(listen))
        if not config_file:
            config.insert_json5("scouting/multicast/enabled", "false")
        for path, value in (extra or {}).items():
            config.insert_json5(path, json.dumps(value))
        return ZenohSession(zenoh.open(config))
    except zenoh.ZError as exc:
        raise LinkError(f"zenoh router: {zenoh_message(exc)}", "check --listen "
                        "(tcp/<address>:<port>, the port free) and --config") from None


def secured(args: argparse.Namespace) -> dict[str, Any]:
    """zenoh's TLS and access control for the router, from --tls, --robot and --base."""
    if not args.tls:
        if args.robot or args.base:
            raise LinkError("--robot and --base name robots by their certificates: they need "
                            "--tls", "add --tls DIR (make DIR with 'rosgate certs')")
        return {}
    try:
        extra: dict[str, Any] = {"transport/link/tls": zenoh_tls(args.tls, args.name)}
    except FileNotFoundError as exc:
        raise LinkError(f"zenoh router: no certificate {exc}",
                        f"make it with 'rosgate certs --out {args.tls} {args.name}'") from None
    if args.robot or args.base:
        extra["access_control"] = access_control(args.prefix, args.robot, args.base,
                                                 [TOKENS])
    return extra


def run(args: argparse.Namespace) -> int:
    listen = args.listen or ([] if args.config else [LISTEN_TLS if args.tls else LISTEN])
    extra = secured(args)
    signals = stop_on_signals()
    session = open_router(listen, args.config, extra)
    log.info("zenoh router running, listening on %s",
             ", ".join(listen) or f"what {args.config} says")
    if not args.tls:
        log.warning("the router runs without TLS: any zenoh session that reaches it may join "
                    "(rosgate router --tls DIR, docs/fleets.md)")
    try:
        wait_for_signal(signals)
    finally:
        log.info("stopping")
        session.close()
    return 0


ROUTER = Command("router", "run a zenoh router for bridges to meet at, until stopped", run,
                 arguments)


def certs_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="the folder (the CA is made there once, then reused)")
    parser.add_argument("names", nargs="+", metavar="NAME",
                        help="a bridge's name (bridge.name) or the router's (router)")


def certs(args: argparse.Namespace) -> int:
    for path in make(args.out, args.names):
        print(f"wrote {path}")
    return 0


CERTS = Command("certs", "make a fleet CA and TLS certificates for zenoh (bridges, router)",
                certs, certs_arguments)
