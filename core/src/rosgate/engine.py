"""A bridge's lifecycle: prepare (resolve the file, refuse open entries unless ``insecure:
true``), start (ROS node, router, role, monitors, status socket), keep house (stale warnings,
the status to the monitors each second, a summary line each minute), stop in reverse order.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from dataclasses import dataclass
from typing import Any

from .bus import BusTransport, Unauthenticated
from .config import BridgeConfig, Direction, Role, load
from .discovery import OWN_NAMESPACE
from .errors import ConfigError, OptionError
from .links.lifetime import Lifetime
from .monitor import Monitor, Status, Watched
from .options import parse
from .plugins import Plugins
from .resolver.plan import Plan, Resolver
from .roles import Bridge
from .roles import Role as BridgeRole
from .roles.client import ClientRole
from .roles.peer import PeerRole
from .roles.server import ServerRole
from .ros import RosNode
from .router import Router
from .routes import ReceiveRoute, Route
from .runtime import RUNTIME_VARIABLE, NotPrivate, StatusServer, private_folder, runtime_dir
from .spec import ServiceSpec, TopicSpec
from .status import collect, summary

log = logging.getLogger("rosgate")

STATS_EVERY = float(os.environ.get("ROSGATE_STATS_EVERY", "60"))
STATUS_EVERY = 1.0  # seconds between two statuses handed to the monitors
#: the bridge: keys that ask for a monitor, and the distribution that has one of that name
MONITOR_KEYS = {"diagnostics": "rosgate-diagnostics", "metrics": "rosgate-metrics-prometheus"}

ROLES: dict[Role, type[BridgeRole]] = {Role.PEER: PeerRole, Role.CLIENT: ClientRole,
                                       Role.SERVER: ServerRole}


@dataclass(frozen=True)
class OpenEntry:
    """An entry whose frames reach ROS here unauthenticated (a receiving topic, a service)."""

    key: str  # where the file says it: topics[0].cipher, services[1].framing
    name: str  # its ROS name here
    why: str  # what leaves it open, in a few words
    fix: str
    at: str | None = None  # where the fix goes when not at the entry: plugins.zenoh.tls

    def __str__(self) -> str:
        return f"{self.key} ({self.name}: {self.why})"


def open_entries(plan: Plan) -> list[OpenEntry]:
    """The entries of ``plan`` that carry ROS traffic into this side without authentication:
    neither keyed by a handshake nor by an authenticating cipher's key from the file. A
    listening microcontroller entry (no envelope, so no cipher) is closed only by
    ``bridge.allow``; a bus entry without a keyed cipher, only by a bus whose every link
    authenticates the far side (:meth:`BusTransport.unauthenticated`)."""
    cfg = plan.config
    found: list[OpenEntry] = []
    # a pattern is judged by the spec its plugins were checked with: every name it finds has it
    patterns = {id(f.checked): f.name for f in plan.patterns
                if isinstance(f.checked, TopicSpec | ServiceSpec)}
    entries: list[TopicSpec | ServiceSpec] = [
        *plan.topics, *plan.services, *(f.checked for f in plan.patterns if id(f.checked) in
                                        patterns), *plan.action_parts]
    for n, p in enumerate(entries):
        t = p.config
        is_topic = isinstance(p, TopicSpec)
        if is_topic and t.direction is Direction.TRANSMIT:
            continue
        part = n >= len(entries) - len(plan.action_parts)  # an action's: said once, as the action
        key = f"{'actions' if part else 'topics' if is_topic else 'services'}[{p.index}]"
        if part and any(f.key.startswith(f"{key}.") for f in found):
            continue
        name = f"action {plan.actions[p.index].config.action}" if part else \
            patterns.get(id(p), p.name)
        link = f"{t.transport}:{t.port}" if t.port else t.transport
        statically_keyed = _keyed(p)
        if isinstance(p.transport, BusTransport):
            door = None if statically_keyed else p.transport.unauthenticated()
            if door is not None:
                found.append(_on_open_bus(cfg, key, name, p, door))
            continue
        if t.framing.bare:
            # a call made here goes out on a connection of its own: only a listening port
            # takes what anyone sends
            if not cfg.allow and t.direction is Direction.RECEIVE:
                found.append(OpenEntry(
                    f"{key}.framing", name, f"framing {t.framing} on {link}, taken from "
                    "anyone", "name the microcontroller's addresses in bridge.allow: "
                    "[192.168.0.20]; or, on a network you trust entirely, insecure: true"))
            continue
        session_keyed = cfg.secure and p.cipher is None  # the resolver leaves it to the session
        if not (session_keyed or statically_keyed):
            # a key file ranks below identities: what it leaves open is said with it
            fix = ("give both peers identities (bridge.identity, peer_key, handshake_port: "
                   "docs/security.md); less safe, a cipher keyed from a file both peers hold "
                   "(cipher: aead, plugins: {aead: {key_file: aead.key}}): whoever copies it "
                   "from either machine reads every frame, recorded or to come, and writes to "
                   "both sides, and a peer that loses its state folder takes frames captured "
                   "before once each" if cfg.role is Role.PEER
                   else "use a cipher the session keys (aead, nacl, fernet)")
            found.append(OpenEntry(f"{key}.cipher", name, f"cipher {t.cipher} on {link}",
                                   f"{fix}; or, on a network you trust entirely, insecure: true"))
    return found


def _keyed(p: TopicSpec | ServiceSpec) -> bool:
    """Sealed by an authenticating cipher keyed from the file."""
    return not p.config.framing.bare and p.cipher is not None and p.cipher_cls is not None \
        and p.cipher_cls.authenticates


def _on_open_bus(cfg: BridgeConfig, key: str, name: str, p: TopicSpec | ServiceSpec,
                 door: Unauthenticated) -> OpenEntry:
    """A bus entry that takes frames from whoever reaches the bus: said at the bus's option
    (at the entry when the file has no options for the bus)."""
    plugin = f"plugins.{p.transport.name}"
    sealed = "" if p.config.framing.bare else (
        "; or seal the entry with a cipher keyed from a file (cipher: aead, plugins: {aead: "
        "{key_file: aead.key}})")
    return OpenEntry(f"{key}.transport", name, f"{p.transport.name}: {door.why}",
                     f"{door.fix}{sealed}; or, on a network you trust entirely, bridge.insecure: "
                     "true", None if plugin not in cfg.lines else
                     f"{plugin}.{door.option}" if door.option else plugin)


class Engine:
    def __init__(self, config: BridgeConfig, plugins: Plugins | None = None,
                 domain_id: int | None = None):
        self.config = config
        self.plugins = plugins or Plugins.discover()
        self.domain_id = domain_id
        self.resolver = Resolver(config, self.plugins)
        self.plan: Plan | None = None
        self.open_doors: list[OpenEntry] = []  # what insecure: true leaves open
        self.life = Lifetime()
        self.ros: RosNode | None = None
        self.router: Router | None = None
        self.role: BridgeRole | None = None
        self.monitors: list[Monitor] = []
        self.status_server: StatusServer | None = None
        self.started = time.monotonic()
        self._monitor_classes: list[tuple[type[Monitor], Any]] = []

    def prepare(self) -> Engine:
        """Resolve the file; :class:`ConfigError` for the first mistake, or for the first
        entry anyone could write to (unless the file says ``insecure: true``)."""
        plan = self.resolver.plan()
        self.open_doors = open_entries(plan)
        if self.open_doors and not self.config.insecure:
            first = self.open_doors[0]
            more = len(self.open_doors) - 1
            also = f" (and {more} more {'entry' if more == 1 else 'entries'})" if more else ""
            entry = f" ({first.key.rpartition('.')[0]})" if first.at else ""
            raise self.config.error(first.at or first.key, f"anyone who reaches this bridge can "
                                    f"write to {first.name}{entry}: {first.why}{also}", first.fix)
        self.plan = plan
        self._monitor_classes = self._wanted_monitors()
        return self

    def insecure_warning(self) -> str | None:
        """What to say on every start of a file that says ``insecure: true``: the entries
        anyone can write to, by name."""
        cfg = self.config
        if not cfg.insecure:
            return None
        if cfg.role is not Role.PEER:
            return (f"INSECURE: {cfg.file} runs without authentication (bridge.insecure: true): "
                    "anyone who can reach it can read and send its topics and call its "
                    "services. Set up identities: docs/security.md")
        entries = ", ".join(map(str, self.open_doors)) or "none of its entries, as it stands"
        return (f"INSECURE: {cfg.file} says insecure: true: anyone who can reach it can write "
                f"to {entries}. Set up identities or keyed ciphers: docs/security.md")

    def _wanted_monitors(self) -> list[tuple[type[Monitor], Any]]:
        """The monitors the file asks for (bridge: keys, plugins: tables), with their options."""
        cfg, found = self.config, []
        names = [name for name in MONITOR_KEYS if getattr(cfg, name)]
        other = {name for kind, name in self.plugins.registered if kind != "monitor"}
        names += [name for name in cfg.plugins if name not in names and name not in other]
        for name in names:
            registration = self.plugins.get("monitor", name)
            if registration is None:
                if name not in MONITOR_KEYS:
                    continue  # a plugins: table of a plugin that is no monitor
                message, _ = self.plugins.explain_missing("monitor", name)
                install = f"pip install {MONITOR_KEYS[name]}"
                if f"bridge.{name}" not in cfg.lines:  # on by default: the bridge runs without
                    # and says so where something stands in the way (a block, a failed import);
                    # a monitor never installed is one the user did not want: said at -v only
                    troubled = name in self.plugins.blocked or \
                        any(f.plugin == name for f in self.plugins.failures)
                    log.log(logging.WARNING if troubled else logging.DEBUG,
                            "%s: no %s: %s (%s, or set bridge.%s: false)", cfg.name, name,
                            message, install, name)
                    continue
                raise cfg.error(f"bridge.{name}", message, f"{install}, or remove {name}:")
            try:
                options = parse(registration.cls, cfg.plugins.get(name) or {})
            except OptionError as exc:
                raise self.resolver.option_error(name, exc, f"bridge.{name}") from None
            found.append((registration.cls, options))
        return found

    def start(self) -> Engine:
        if self.plan is None:
            self.prepare()
        assert self.plan is not None
        # a status folder another user made: refused before anything runs (NotPrivate); one
        # that cannot be made is said below, and the bridge runs without a status socket
        with contextlib.suppress(OSError):
            private_folder(runtime_dir(), RUNTIME_VARIABLE)
        # in rosgate's own namespace: what a bridge publishes, no bridge's pattern finds
        self.ros = RosNode(self.config.name, self.domain_id, namespace=OWN_NAMESPACE)
        self.router = Router(self.ros)
        try:
            self.role = ROLES[self.config.role](
                Bridge(self.config, self.plan, self.resolver, self.router, self.life))
            self.role.start()
            watched = Watched(self.config, self.status, self.ros, self.life.stopping)
            for cls, options in self._monitor_classes:
                monitor = cls(watched, options)
                monitor.start()
                self.monitors.append(monitor)
        except (ConfigError, NotPrivate):  # a server's state folder another user made
            self.stop()
            raise
        try:
            self.status_server = StatusServer(self.config.name, self.status)
        except NotPrivate:  # made another user's since the check above
            self.stop()
            raise
        except OSError as exc:  # rosgate top will not see this bridge; the bridge runs on
            log.warning("%s: no status socket (rosgate top): %s", self.config.name, exc)
        threading.Thread(target=self._housekeeping, name="housekeeping", daemon=True).start()
        log.info("%s: running as %s with %d topic(s) and %d service(s)%s", self.config.name,
                 self.config.role, len(self.plan.topics), len(self.plan.services),
                 f" and {len(self.plan.actions)} action(s)" if self.plan.actions else "")
        return self

    def stop(self) -> None:
        if self.life.stopping.is_set():
            return
        self.life.stopping.set()
        if self.status_server is not None:
            self.status_server.close()
        for monitor in self.monitors:
            monitor.stop()
        if self.role is not None:
            self.role.wind_down()
        if self.router is not None:
            self.router.log_stats()  # before the routes and their counters go
            for link in self.life.links():
                if link.counters.frames_out or link.counters.frames_in:
                    log.info("link %s: %s", link.name, link.counters.line())
        if self.role is not None:
            self.role.stop()
        self.life.close_all()
        if self.router is not None:
            self.router.close()
        if self.ros is not None:
            self.ros.close()

    def reload(self, path: str) -> None:
        """SIGHUP: a server applies the ``clients:`` of its file as it is now (a file that no
        longer loads is reported and the running policy kept)."""
        if not isinstance(self.role, ServerRole):
            log.info("SIGHUP: nothing to reload for a %s", self.config.role)
            return
        try:
            fresh = load(path)
        except ConfigError as exc:
            log.error("SIGHUP: %s; the running policy stays", exc)
            return
        self.role.reload(fresh.clients)

    def status(self) -> Status:
        """What the bridge does now: every route's and link's counters (:mod:`rosgate.status`)."""
        return collect(self.config, self.role, self.router, self.life, self.started)

    def _housekeeping(self) -> None:
        now = time.monotonic()
        next_status, next_summary = now + STATUS_EVERY, now + STATS_EVERY
        last_summary: Status | None = None
        while not self.life.stopping.wait(0.25):
            assert self.router is not None
            now = time.monotonic()
            self.router.warn_stale(self.config, now)
            if now < next_status:
                continue
            next_status = now + STATUS_EVERY
            status = self.status()
            for monitor in self.monitors:
                try:
                    monitor.update(status)
                except Exception:  # one monitor's bug must not stop the others
                    self.router.warner.bug(f"monitor_{monitor.name}",
                                           f"monitor {monitor.name!r} failed")
            if now >= next_summary:
                next_summary = now + STATS_EVERY
                log.info("%s", summary(status, last_summary))
                last_summary = status

    # -- what a running bridge carried ----------------------------------------------------------
    def routes(self) -> list[Route]:
        return self.router.snapshot() if self.router is not None else []

    def stats(self) -> dict[str, Any]:
        """Counters per route, drops that belong to no topic, and what each open link carried
        (frames, datagrams or writes, how many frames were coalesced)."""
        stats = self.router.stats() if self.router is not None else {"routes": {}, "link_drops": {}}
        stats["links"] = {link.name: link.counters.snapshot() for link in self.life.links()}
        return stats

    @property
    def link_drops(self) -> dict[str, int]:
        return dict(self.router.link_drops) if self.router is not None else {}

    @property
    def receivers(self) -> dict[int, ReceiveRoute]:
        return dict(self.router.receivers) if self.router is not None else {}
