"""``rosgate router``: a zenoh router for bridges to meet at, until SIGINT or SIGTERM.

Bridges in ``mode: client`` need one at start; peers attach when one comes. ``--listen`` takes
zenoh endpoints (``tcp/0.0.0.0:7447``, repeatable); ``--config`` takes zenoh's own JSON5 file, as
``zenohd -c`` does. Without ``--config`` multicast scouting is off, as for the bridges.
"""

from __future__ import annotations

import argparse
import json
import logging

import zenoh

from rosgate import Command, LinkError
from rosgate.commands import stop_on_signals, wait_for_signal

from .transport import ZenohSession, zenoh_message

LISTEN = "tcp/0.0.0.0:7447"

log = logging.getLogger("rosgate")


def arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                        help=f"where to listen, repeatable (default {LISTEN})")
    parser.add_argument("--config", metavar="FILE",
                        help="zenoh's own configuration file (JSON5, as for zenohd -c)")


def open_router(listen: list[str], config_file: str | None) -> ZenohSession:
    """A zenoh session in router mode; :class:`rosgate.LinkError` when zenoh refuses."""
    try:
        config = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
        config.insert_json5("mode", json.dumps("router"))
        if listen:
            config.insert_json5("listen/endpoints", json.dumps(listen))
        if not config_file:
            config.insert_json5("scouting/multicast/enabled", "false")
        return ZenohSession(zenoh.open(config))
    except zenoh.ZError as exc:
        raise LinkError(f"zenoh router: {zenoh_message(exc)}", "check --listen "
                        "(tcp/<address>:<port>, the port free) and --config") from None


def run(args: argparse.Namespace) -> int:
    listen = args.listen or ([] if args.config else [LISTEN])
    stop = stop_on_signals()
    session = open_router(listen, args.config)
    log.info("zenoh router running, listening on %s",
             ", ".join(listen) or f"what {args.config} says")
    try:
        wait_for_signal(stop)
    finally:
        log.info("stopping")
        session.close()
    return 0


ROUTER = Command("router", "run a zenoh router for bridges to meet at, until stopped", run,
                 arguments)
