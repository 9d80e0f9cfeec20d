"""Bridge what appears: the names a transmit pattern entry matches on this side's ROS graph, looked
at every :data:`LOOK_EVERY` seconds. A name that appears (a publisher of a topic that is not
rosgate's own, so two bridges never carry each other's messages back) is handed to the role,
which makes its route; a name whose publishers all went is handed back after the grace period.
What a pattern may not make is said once per name and counted: a denied name is silently left
out, a name with publishers of two types and a name past ``max_routes`` are refused."""

from __future__ import annotations

import logging
import threading
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from .config import BridgeConfig, Direction
from .config.kinds import ROS_NAME_MAX
from .config.patterns import denied, far_name, is_pattern, matches
from .errors import ConfigError
from .policy import is_action_part

if TYPE_CHECKING:  # ``import rosgate`` (BusPattern) stays light: the resolver's plugins load later
    from .resolver.plan import Pattern

log = logging.getLogger("rosgate")

LOOK_EVERY = 0.25  # seconds between two looks at the graph: a name's route within 1 s
#: the namespace of every bridge's node (a hidden one, as ROS's tools take a leading '_'): what
#: bridges publish is never found, so two bridges never carry each other's messages back
OWN_NAMESPACE = "/_rosgate"


@dataclass
class Found:
    """A name a pattern found, and what its route is."""

    pattern: Pattern
    name: str
    type: str
    route: Any = None  # what the role made of it
    gone_since: float | None = None  # monotonic time its last publisher went (None: it has some)


@dataclass
class Refusals:
    """What the patterns refused, by reason, and the names already said (said once each)."""

    counts: Counter = field(default_factory=Counter)
    said: set[tuple[str, str]] = field(default_factory=set)

    def refuse(self, reason: str, name: str, message: str) -> None:
        if (reason, name) not in self.said:  # a name is refused once, not at every look
            self.said.add((reason, name))
            self.counts[reason] += 1
            log.error("%s", message)


def publishers(node: Any) -> dict[str, set[str]]:
    """Each topic with publishers on the graph that are not a rosgate node's: their types (one
    query per node, not per topic: an idle bridge with hundreds of topics stays idle)."""
    return _by_node(node, node.get_publisher_names_and_types_by_node)


def servers(node: Any) -> dict[str, set[str]]:
    """Each service with servers on the graph that are not a rosgate node's: their types."""
    return _by_node(node, node.get_service_names_and_types_by_node)


def action_servers(node: Any) -> dict[str, set[str]]:
    """Each action with servers on the graph that are not a rosgate node's: their types
    (``pkg/action/X``, as rclpy reads them from the action's services)."""
    from rclpy.action import get_action_server_names_and_types_by_node

    return _by_node(node, lambda name, namespace: get_action_server_names_and_types_by_node(
        node, name, namespace), parts=True)


def _by_node(node: Any, query: Callable[[str, str], Any],
             parts: bool = False) -> dict[str, set[str]]:
    found: dict[str, set[str]] = {}
    for name, namespace in node.get_node_names_and_namespaces():
        if namespace == OWN_NAMESPACE:
            continue
        try:
            entities = query(name, namespace)
        except Exception:  # the node went between the two questions: it has nothing now
            continue
        for entity, types in entities:
            # an action's topics and services cross as the action (``parts``: its name is one)
            if parts or not is_action_part(entity):
                found.setdefault(entity, set()).update(types)
    return found


#: what a kind of pattern entry finds on its side's graph, and who has it
GRAPHS: dict[str, tuple[Callable[[Any], dict[str, set[str]]], str]] = {
    "topics": (publishers, "publisher"), "services": (servers, "server"),
    "actions": (action_servers, "action server")}


class Discovery:
    """The patterns of a plan that find names on this side (``kind`` topics: transmit ones;
    services and actions: receive ones, whose calls and goals come from the far side), watched
    on ``node``'s graph.
    ``add(found)`` makes a name's route (it returns it, or None when it could not);
    ``drop(found)`` takes it down; ``changed()`` follows a look that added or dropped any (the
    far side is told once)."""

    def __init__(self, config: BridgeConfig, patterns: list[Pattern], node: Any,
                 add: Callable[[Found], Any], drop: Callable[[Found], None],
                 clock: Callable[[], float], changed: Callable[[], None] = lambda: None,
                 kind: str = "topics"):
        self.config, self.kind = config, kind
        here = Direction.TRANSMIT if kind == "topics" else Direction.RECEIVE
        self.patterns = [p for p in patterns if p.section == kind and p.entry.direction is here]
        self.graph, self.holder = GRAPHS[kind]
        entries: list[Any] = getattr(config, kind)
        # a name listed as an entry is that entry's, not a pattern's
        self.listed = {getattr(e, kind[:-1]) for e in entries if not e.pattern}
        self.node = node
        self.add, self.drop, self.clock, self.changed = add, drop, clock, changed
        self.found: dict[str, Found] = {}
        self.refusals = Refusals()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"discovery-{kind}", daemon=True)

    def start(self) -> None:
        if self.patterns:
            for p in self.patterns:
                log.info("%s: %s %s bridges its names as they appear", self.config.name,
                         _where(p), p.name)
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2)

    def _run(self) -> None:
        while not self._stop.wait(LOOK_EVERY):
            try:
                self.look(self.graph(self.node))
            except Exception:  # a graph query that failed (shutting down): the next look retries
                log.debug("discovery: could not read the graph", exc_info=True)

    def look(self, graph: dict[str, set[str]]) -> None:
        """Routes for the names that appeared, none for the names gone past the grace."""
        now, had = self.clock(), set(self.found)
        for name, types in sorted(graph.items()):
            if name in self.found:
                found = self.found[name]
                found.gone_since = None
                if types != {found.type}:  # DDS never matches the others to its route
                    self.refusals.refuse(
                        "types_differ", name, f"{_where(found.pattern)} {found.pattern.name}: "
                        f"{name} now has {self.holder}s of {' and '.join(sorted(types))}: its "
                        f"route carries {found.type} only")
                continue
            pattern = self._pattern_of(name)
            if pattern is not None:
                self._appeared(pattern, name, types)
        for name, found in list(self.found.items()):
            if name in graph:
                continue
            if found.gone_since is None:
                found.gone_since = now
            elif now - found.gone_since >= self.config.pattern_grace:
                del self.found[name]
                self.drop(found)
                log.info("%s: %s is gone (no %s for %g s): its route is removed",
                         self.config.name, name, self.holder, self.config.pattern_grace)
        if set(self.found) != had:
            self.changed()

    def matching(self, graph: dict[str, set[str]]) -> dict[str, list[str]]:
        """What each pattern takes of ``graph`` now, by the pattern as written: ``name [type]``
        (or why it would be refused)."""
        taken: dict[str, list[str]] = {p.name: [] for p in self.patterns}
        for name, types in sorted(graph.items()):
            pattern = self._pattern_of(name)
            if pattern is None:
                continue
            if len(types) > 1:
                taken[pattern.name].append(f"{name} (refused: {' and '.join(sorted(types))})")
            elif pattern.entry.type and pattern.entry.type not in types:
                taken[pattern.name].append(f"{name} (left out: {next(iter(types))})")
            else:
                taken[pattern.name].append(f"{name} [{next(iter(types))}]")
        return taken

    def _pattern_of(self, name: str) -> Pattern | None:
        """The first pattern that takes ``name`` (not listed, not denied), or None."""
        if name in self.listed or denied(name, self.config.deny):
            return None
        for p in self.patterns:
            if matches(p.name, name) and not denied(name, p.entry.deny):
                return p
        return None

    def _appeared(self, pattern: Pattern, name: str, types: set[str]) -> None:
        entry, where = pattern.entry, _where(pattern)
        if len(types) > 1:
            self.refusals.refuse("types_differ", name, f"{where} {pattern.name}: {name} is "
                                 f"refused: its {self.holder}s give {' and '.join(sorted(types))}"
                                 "; one name carries one type")
            return
        (type_name,) = types
        if entry.type and type_name != entry.type:
            self.refusals.refuse("other_type", name, f"{where} {pattern.name}: {name} is left "
                                 f"out: it publishes {type_name}, the entry says {entry.type}")
            return
        made = sum(1 for f in self.found.values() if f.pattern is pattern)
        if made >= entry.max_routes:
            self.refusals.refuse("max_routes", name, f"{where} {pattern.name}: {name} is refused: "
                                 f"the pattern has made its {entry.max_routes} routes "
                                 "(max_routes)")
            return
        found = Found(pattern, name, type_name)
        found.route = self.add(found)
        if found.route is None:
            self.refusals.refuse("unroutable", name, f"{where} {pattern.name}: {name} "
                                 f"({type_name}) could not be bridged (said above)")
            return
        self.found[name] = found
        log.info("%s: %s %s found %s (%s): bridged", self.config.name, where, pattern.name, name,
                 type_name)

    def status(self) -> dict[str, Any]:
        return {"found": sorted(self.found), "refused": dict(self.refusals.counts)}


class BusPattern:
    """A peer's receiving topic pattern on a bus (``topic: /robot1/**`` with ``transport:
    zenoh``), as its bus role watches the bus for it (:meth:`rosgate.BusRole.pattern`): the bus
    role hands :meth:`take` each topic announced there, by its name on the bus and its type,
    and makes the route of the spec it gives. Called from one thread (the bus link's)."""

    def __init__(self, config: BridgeConfig, pattern: Pattern,
                 make: Callable[[Pattern, str, str], Any]):
        self.config, self.pattern, self._make = config, pattern, make
        entry = pattern.entry
        #: what every route it makes shares (transport, codec, key...): a stand-in name's spec
        self.spec: Any = pattern.checked
        #: the names it takes on the bus (the entry's ``remote``: ``/fleet/robot1/**``)
        self.remote: str = entry.remote if "remote" in entry.lines else pattern.name
        self.listed = {t.topic for t in config.topics if not t.pattern}
        #: the routes' specs it made, by the name on the bus
        self.made: dict[str, Any] = {}
        self.refusals = Refusals()

    def take(self, far: str, type_name: str) -> Any:
        """The spec of the route for the topic announced on the bus as ``far`` (a ROS name) of
        ``type_name``, or None: the pattern does not take it (outside it, denied, listed, of
        another type than the entry's), has it already, or refuses it (past ``max_routes``,
        its plugins cannot carry it: said once and counted)."""
        p, entry = self.pattern, self.pattern.entry
        if far in self.made or not type_name or not matches(self.remote, far):
            return None
        name = far_name(self.remote, p.name, far)
        if (name in self.listed or denied(name, entry.deny) or denied(name, self.config.deny)
                or entry.type not in ("", type_name)):
            return None
        where = f"{_where(p)} {p.name}"
        if len(self.made) >= entry.max_routes:
            self.refusals.refuse("max_routes", name, f"{where}: {name} is refused: the pattern "
                                 f"has made its {entry.max_routes} routes (max_routes)")
            return None
        try:
            spec = self._make(p, name, type_name)
        except ConfigError as exc:
            self.refusals.refuse("unroutable", name, f"{where}: {name} ({type_name}) cannot be "
                                 f"bridged: {exc}")
            return None
        self.made[far] = spec
        log.info("%s: %s found %s (%s) on %s: bridged", self.config.name, where, name,
                 type_name, self.spec.transport.name)
        return spec

    def forget(self, far: str) -> None:
        """The route of ``far`` was removed (its publishers gone for ``bridge.pattern_grace``):
        said, and the name may be taken again."""
        spec = self.made.pop(far)
        log.info("%s: %s is gone (no publisher for %g s): its route is removed",
                 self.config.name, spec.name, self.config.pattern_grace)

    def status(self) -> dict[str, Any]:
        return {"found": sorted(s.name for s in list(self.made.values())),
                "refused": dict(self.refusals.counts)}


def _where(pattern: Pattern) -> str:
    return f"{pattern.section}[{pattern.index}]"


MAX_WATCHED = 64  # patterns one client may ask its server to watch


def made_by(founds: Iterable[Found], specs: Sequence[Any]) -> list[str | None]:
    """The pattern (as written) that found each of ``specs`` (None: a name gone), for the
    ``patterns`` a client's hello and ``found`` say beside its ``found`` names."""
    by_spec = {id(f.route): f.pattern.name for f in founds}
    return [None if spec is None else by_spec.get(id(spec)) for spec in specs]


def said_patterns(message: dict[str, Any], first: int) -> dict[int, str]:
    """What a client's message says made each name it found (``patterns``, in the order of
    ``found``), by the entry's index (the found names follow its ``first`` listed entries);
    what is not a pattern is left out: it is shown to operators, never obeyed."""
    items = message.get("patterns", [])
    if not isinstance(items, list):
        return {}
    return {first + i: p for i, p in enumerate(items)
            if isinstance(p, str) and is_pattern(p) and len(p) <= ROS_NAME_MAX}


def watched(message: dict[str, Any], key: str = "watch") -> list[str]:
    """The server-side patterns a client's hello asks the server to watch for it (``watch``: its
    receive topic patterns' ``remote``; ``watch_services``, ``watch_actions``: its transmit
    service and action patterns'); what is not a pattern is left out."""
    items = message.get(key, [])
    if not isinstance(items, list):
        return []
    return [p for p in items[:MAX_WATCHED] if isinstance(p, str) and is_pattern(p)
            and len(p) <= ROS_NAME_MAX and p.startswith("/")]


class Offers:
    """A server's look at its graph for the receive patterns of its clients: to each session,
    the names under its patterns that have a publisher here (one type each, not rosgate's, not
    in ``bridge.deny``), with their types, said whenever that changes; a name whose publishers
    went is offered for ``bridge.pattern_grace`` more seconds."""

    def __init__(self, config: BridgeConfig, node: Any, sessions: Callable[[], list[Any]],
                 say: Callable[[Any, dict[str, dict[str, str]]], None],
                 clock: Callable[[], float]):
        self.config, self.node, self.sessions, self.say, self.clock = (
            config, node, sessions, say, clock)
        #: session id -> what it was last offered, by kind
        self.said: dict[int, dict[str, dict[str, str]]] = {}
        #: by kind, each name -> its type, when last seen here
        self.seen: dict[str, dict[str, tuple[str, float]]] = {kind: {} for kind in GRAPHS}

    def look(self) -> None:
        sessions = [s for s in self.sessions() if s.watch or s.watch_services or s.watch_actions]
        if not sessions:
            return
        now = self.clock()
        for kind, (graph, _) in GRAPHS.items():
            if not any(_watches(s, kind) for s in sessions):
                continue  # a kind nobody watches is not looked at
            seen = self.seen[kind]
            for name, types in graph(self.node).items():
                if len(types) == 1 and not denied(name, self.config.deny):
                    seen[name] = (next(iter(types)), now)
            for name in [n for n, (_, at) in seen.items()
                         if now - at > self.config.pattern_grace]:
                del seen[name]
        for session in sessions:
            offer = {kind: {name: type_name for name, (type_name, _) in self.seen[kind].items()
                            if any(matches(p, name) for p in _watches(session, kind))}
                     for kind in GRAPHS}
            if offer != self.said.get(session.id) and session.down_since is None:
                self.said[session.id] = offer
                self.say(session, offer)
        live = {s.id for s in sessions}
        for gone in [i for i in self.said if i not in live]:
            del self.said[gone]

    def forget(self, session: Any) -> None:
        """Say everything again to ``session`` at the next look (it connected again)."""
        self.said.pop(session.id, None)


def _watches(session: Any, kind: str) -> list[str]:
    """The patterns of ``kind`` a server watches for ``session``'s client."""
    return {"topics": session.watch, "services": session.watch_services,
            "actions": session.watch_actions}[kind]
