"""Why something was dropped: one enumeration, each reason with the sentence the docs show
(docs/operators.md's table is generated from it). Every drop is counted by reason, per topic
or per bridge, and counting takes a :class:`Drop` or a plugin's reason made by :func:`declare`,
never a bare string, so a new reason always comes with its sentence.
"""

from __future__ import annotations

from collections.abc import Callable
from enum import StrEnum
from typing import Any


class Drop(StrEnum):
    """A reason the core counts; ``doc`` says when it happens."""

    doc: str

    def __new__(cls, value: str, doc: str = "") -> Drop:
        member = str.__new__(cls, value)
        member._value_ = value
        member.doc = doc
        return member

    def __repr__(self) -> str:  # a counter's dict in a log line reads as it always has
        return repr(self.value)

    # sending
    RATE_LIMIT = "rate_limit", "faster than the topic's `max_rate`"
    SUPERSEDED = "superseded", "a latest-only topic's waiting message was replaced by a newer one"
    TOO_LATE = "too_late", ("a best-effort message waited longer than its `max_delay` (to be "
                            "taken, in the send queue or in the receive buffer), or, without "
                            "one, over 25 ms (and over the time between the topic's messages) "
                            "to be taken or in the receive buffer while that "
                            "queue had stood behind for 100 ms on end (the oldest goes first); "
                            "or any message that waited longer than its `max_delay` for the "
                            "server to come back")
    OVERLOAD = "overload", ("a best-effort message (without a `max_delay` of its own) that "
                            "waited over 20 ms in a link's send queue while its topic had been "
                            "behind there for 200 ms on end: a link offered more than it carries "
                            "sheds the oldest, so what arrives stays fresh")
    QUEUE_FULL = "queue_full", ("a queue had no room: a link's send queue at its `frames` or "
                                "`bytes` limit, a bus link's queue, or what a link that is down "
                                "or a server out of reach holds (its oldest message goes)")
    LINK_DOWN = "link_down", ("the link was closed or down, or the server out of reach, with "
                              "the frame or call still waiting (or sent to a server that "
                              "restarted)")
    SEND_ERROR = "send_error", "the transport failed to send the frame"
    NO_PEER_YET = "no_peer_yet", "the far side's address is not known yet"
    NO_SESSION_KEY = "no_session_key", "the session's key is not there yet, or is gone"
    ENCODE_ERROR = "encode_error", "the codec could not write the message"
    TOO_LARGE = "too_large", "a service's request (or a board's answer) over its `max_request`"
    TOO_LARGE_FOR_BARE_FRAMING = "too_large_for_bare_framing", \
        "a frame with `framing: none` larger than one datagram of the link"
    SESSION_RESET = "session_reset", \
        "waited under a session's topic ids that a new session no longer has"
    TOO_MANY_CALLS = "too_many_calls", "a service had its most calls in progress"
    NO_SERVER = "no_server", "no server for the call: none on the bus, or no ROS server running"
    TIMEOUT = "timeout", "a call that got no answer within its `timeout`"
    REMOTE_FAILURE = "remote_failure", "the far side answered the call as failed"
    SERVER_ERROR = "server_error", "the ROS server's call failed"
    FOREIGN_GOAL = "foreign_goal", ("an action's cancel, result request, goal id or feedback "
                                    "about a goal another client sent: answered as for an "
                                    "unknown goal, or not sent (goals belong to their sender "
                                    "unless the action's rule says `shared`)")
    TOO_MANY_GOALS = "too_many_goals", ("a client's goal past 1,000 of one action still running "
                                        "on the server: not accepted")
    # receiving: the link
    TRANSPORT_ERROR = "transport_error", "the transport failed while receiving (a bug: logged)"
    RECEIVE_BUFFER_FULL = "receive_buffer_full", ("datagrams the kernel dropped because a "
                                                  "link's receive buffer was full: the bridge "
                                                  "did not read them in time (udp, on Linux)")
    OVERSIZED_DATAGRAM = "oversized_datagram", "a datagram longer than the link's `max_frame`"
    BAD_FRAGMENT = "bad_fragment", "a fragment whose header or size is impossible"
    BAD_BATCH = "bad_batch", "a batch datagram whose lengths run past its end"
    BAD_LENGTH = "bad_length", \
        "a stream frame whose length is impossible, or over `max_frame_before_auth` before trust"
    FRAGMENT_LOST = "fragment_lost", "a frame's fragments stopped coming before it was whole"
    REASSEMBLY_OVERFLOW = "reassembly_overflow", \
        "partial frames over the reassembly's count or memory bound (the oldest goes)"
    NOT_ALLOWED = "not_allowed", "from an address the link does not accept"
    HANDLER_ERROR = "handler_error", "a handler failed (a bug: its traceback is logged)"
    # receiving: the envelope and its route
    TRUNCATED_FRAME = "truncated_frame", "shorter than an envelope"
    FOREIGN_FRAME = "foreign_frame", "does not start with rosgate's envelope"
    VERSION_FRAME = "version_frame", "an envelope of another version"
    UNEXPECTED_FRAME = "unexpected_frame", "an envelope that is not for the key it came on"
    UNNAMED_FRAME = "unnamed_frame", "a bare datagram that does not start with a topic's name"
    UNKNOWN_TOPIC = "unknown_topic", "for a topic this side does not receive"
    UNKNOWN_SERVICE = "unknown_service", "for a service this side does not carry"
    UNKNOWN_KEY = "unknown_key", "sealed under a key this side does not hold (an earlier session)"
    AUTH_FAILED = "auth_failed", "the cipher refused it: wrong key, tampered, or not from the peer"
    DUPLICATE = "duplicate", "its sequence number was seen already (a replay or a copy)"
    STALE = "stale", "older than the replay window"
    REPLAYED = "replayed", ("a peer's frame under a static key sent before this side last "
                            "started (a replay; or the peer's clock and state folder both went "
                            "back: docs/security.md)")
    ORDER_OVERFLOW = "order_overflow", ("a reliable topic's frames held for a missing one, to be "
                                        "published in order, over 4,096 frames or 16 MiB: the "
                                        "gap was given up (its frame counted lost on the way)")
    TYPE_MISMATCH = "type_mismatch", "the far side's message type is not this side's"
    TYPE_NOT_INSTALLED = "type_not_installed", ("the far side's message type is not installed on "
                                                "this side (its log names the package)")
    TYPE_UNHEARD = "type_unheard", ("held for the far side's type announcement beyond the hold's "
                                    "bound (1,000 frames or 16 MiB): the oldest went")
    BAD_ANNOUNCEMENT = "bad_announcement", "an entry's type announcement that cannot be read"
    TOO_MANY_NAMES = "too_many_names", ("a name a far peer announced under this side's receive "
                                        "patterns past what they take (`max_routes`, or 1,000 "
                                        "names in one announcement): no route is made for it")
    ECHO = "echo", ("a message this bridge published itself, taken back by its own subscription "
                    "of the name (peers that both send and receive it): never sent back")
    DECOMPRESSION_ERROR = "decompression_error", \
        "a payload transform this side lacks, or one that could not undo its work"
    DECODE_ERROR = "decode_error", "the codec could not read the payload"
    PUBLISH_ERROR = "publish_error", "ROS refused to publish the message"
    NOT_MATCHED = "not_matched", ("held while the bridge's new publisher matched its "
                                  "subscribers, and pushed out of the full hold or left in it "
                                  "when the route ended")
    LATE_ANSWER = "late_answer", "a service's answer after its call was over"
    # connections and sessions
    ACCEPT_FAILED = "accept_failed", "accepting a connection failed (tried again after a pause)"
    TOO_MANY_CONNECTIONS = "too_many_connections", \
        "past `bridge.limits.connections` (or a port's most calls at once)"
    TOO_MANY_PER_SOURCE = "too_many_per_source", "past `bridge.limits.connections_per_source`"
    TOO_MANY_HANDSHAKES = "too_many_handshakes", "too many handshakes at once"
    HANDSHAKE_TIMEOUT = "handshake_timeout", \
        "a connection that did not finish its handshake within `bridge.limits.handshake_timeout`"
    BAD_HANDSHAKE = "bad_handshake", "a handshake that failed (a wrong key, or not Noise)"
    UNKNOWN_CLIENT_KEY = "unknown_client_key", "a client key the server's `clients:` lacks"
    BAD_HELLO = "bad_hello", "a hello that cannot be read"
    UNEXPECTED_HELLO = "unexpected_hello", "a hello on a side that takes none"
    BEFORE_HANDSHAKE = "before_handshake", "data on a main line before its hello"
    NOT_CONTROL = "not_control", "a frame on a handshake line that is not a control message"
    BAD_CONTROL = "bad_control", "a control message that cannot be read"
    SESSION_ERROR = "session_error", "setting a client's session up failed (a bug: logged)"


class PluginDrop(str):
    """A reason a plugin counts, made by :func:`declare` (with its sentence in ``doc``)."""

    doc: str


#: what a drop is counted by
Reason = Drop | PluginDrop
#: counts a frame that belongs to no topic, per bridge: (the link or port, reason, detail)
LinkDrop = Callable[[Any, Reason, str], None]

_DECLARED: dict[str, PluginDrop] = {}


def declare(name: str, doc: str) -> PluginDrop:
    """A reason of a plugin's own, with the sentence its page shows; the same reason twice is
    one. A name the core uses, or another plugin's with another sentence, is refused."""
    if name in Drop.__members__.values():
        raise ValueError(f"drop reason {name!r} is the core's: count rosgate.drops.Drop({name!r})")
    known = _DECLARED.get(name)
    if known is None:
        known = _DECLARED[name] = PluginDrop(name)
        known.doc = doc
    elif known.doc != doc:
        raise ValueError(f"drop reason {name!r} is declared already: {known.doc!r}")
    return known


def declared() -> list[PluginDrop]:
    """The reasons plugins declared so far (those imported)."""
    return list(_DECLARED.values())


def table() -> str:
    """The Markdown table of every core reason and its sentence."""
    rows = [f"| `{reason}` | {reason.doc} |" for reason in Drop]
    return "\n".join(["| reason | when |", "|---|---|", *rows]) + "\n"
