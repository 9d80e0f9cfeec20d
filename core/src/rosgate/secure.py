"""Authenticated sessions (docs/security.md says what each part gives and why):

* the handshake, ``Noise_IK_25519_ChaChaPoly_BLAKE2s``: the initiator knows the responder's static
  key and sends its own, checked before anything else is parsed; each message ``u16 length |
  message``, bounded in size and time, the prologue binding the protocol version;
* :class:`SecureConnection`, the stream after it: Noise transport records with counter nonces,
  so a reordered, replayed, dropped or altered record ends the connection;
* :class:`KeySchedule`, a session's keys: a root from the responder's fresh secret (HKDF salted
  with the handshake hash), then ``HKDF(root, "rosgate/1 " + label + generation)`` per
  direction, entry and generation; the envelope's epoch (``key id << 24 | generation``) names it;
* :func:`seal_hello`, datagrams that tell a server where a client's link is.
"""

from __future__ import annotations

import os
import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305
from cryptography.hazmat.primitives.hashes import SHA256
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

from .cipher import Cipher
from .errors import LinkError
from .keyring import Changes, Keys, NoKey
from .transport import StreamConnection
from .wire import envelope

NOISE_PROTOCOL = b"Noise_IK_25519_ChaChaPoly_BLAKE2s"
PROLOGUE = b"rosgate/1"
HANDSHAKE_MAX = 256       # bytes of one handshake message (IK's are 96 and 48)
HANDSHAKE_TIMEOUT = 5.0   # seconds for the whole handshake, from the connection's start
RECORD = struct.Struct(">H")
RECORD_MAX = 65535        # a Noise message
CHUNK = RECORD_MAX - 16   # plaintext per record (Poly1305 tag)
GRACE = 10.0              # seconds a previous root still opens frames after a new handshake
GENERATIONS = 1 << 24
HELLO_LABEL = "hello c2s"


class HandshakeError(LinkError):
    """A handshake that failed: not Noise, a wrong or unknown key, too slow, too big."""


def _noise(initiator: bool, identity: bytes, remote: bytes | None = None):
    from noise.connection import Keypair, NoiseConnection

    noise = NoiseConnection.from_name(NOISE_PROTOCOL)
    noise.set_as_initiator() if initiator else noise.set_as_responder()
    noise.set_prologue(PROLOGUE)
    noise.set_keypair_from_private_bytes(Keypair.STATIC, identity)
    if remote is not None:
        noise.set_keypair_from_public_bytes(Keypair.REMOTE_STATIC, remote)
    noise.start_handshake()
    return noise


def _read_message(connection: StreamConnection, deadline: float) -> tuple[bytes, bytes]:
    """One ``u16 length | message`` of the handshake within the deadline, and what came after."""
    buffer = bytearray()
    while True:
        if len(buffer) >= RECORD.size:
            (size,) = RECORD.unpack_from(buffer)
            if size > HANDSHAKE_MAX:
                raise HandshakeError(f"not a handshake (a message of {size} bytes)")
            end = RECORD.size + size
            if len(buffer) >= end:
                return bytes(buffer[RECORD.size:end]), bytes(buffer[end:])
        left = deadline - time.monotonic()
        if left <= 0:
            raise HandshakeError("no handshake in time")
        try:
            data = connection.receive(4096, min(left, 0.5))
        except OSError as exc:
            raise HandshakeError(f"connection failed: {exc}") from None
        if data == b"":
            raise HandshakeError("connection closed during the handshake")
        if data:
            buffer += data


def _send_message(connection: StreamConnection, message: bytes) -> None:
    try:
        connection.send(RECORD.pack(len(message)) + message)
    except OSError as exc:
        raise HandshakeError(f"connection failed: {exc}") from None


def initiate(connection: StreamConnection, identity: bytes, server_key: bytes,
             timeout: float = HANDSHAKE_TIMEOUT) -> SecureConnection:
    """The client's side: prove our identity to the server whose key we know."""
    deadline = time.monotonic() + timeout
    noise = _noise(True, identity, server_key)
    _send_message(connection, noise.write_message(b""))
    message, pending = _read_message(connection, deadline)
    try:
        noise.read_message(message)
    except Exception:  # noiseprotocol raises several kinds; all mean the same here
        raise HandshakeError("the server's answer does not verify (is bridge.server_key the "
                             "server's key?)") from None
    return SecureConnection(connection, noise, server_key, pending)


def respond(connection: StreamConnection, identity: bytes, known: Callable[[bytes], bool],
            timeout: float = HANDSHAKE_TIMEOUT,
            admit: Callable[[], bool] | None = None) -> SecureConnection:
    """The server's side: a client whose static key ``known`` refuses gets no answer at all.
    ``admit``, asked before the Diffie-Hellman, refuses with :class:`Busy` when False."""
    deadline = time.monotonic() + timeout
    noise = _noise(False, identity)
    message, pending = _read_message(connection, deadline)
    if admit is not None and not admit():
        raise Busy("too many handshakes at once")
    try:
        noise.read_message(message)
    except Exception:
        raise HandshakeError("not a handshake for this server's key") from None
    remote = noise.noise_protocol.handshake_state.rs.public_bytes
    if not known(remote):
        raise UnknownKey(remote)
    _send_message(connection, noise.write_message(b""))
    return SecureConnection(connection, noise, remote, pending)


class Busy(HandshakeError):
    """A handshake refused before its Diffie-Hellman: too many at once (from its address)."""


class UnknownKey(HandshakeError):
    def __init__(self, key: bytes):
        super().__init__("a key that is not in clients:")
        self.key = key


class SecureConnection:
    """A stream connection whose bytes travel in Noise transport messages; one thread sends and
    one receives (a :class:`~rosgate.streamlink.link.StreamLink`'s)."""

    def __init__(self, raw: StreamConnection, noise, peer_key: bytes, pending: bytes = b""):
        self.raw = raw
        self.noise = noise
        self.peer_key = peer_key
        self.handshake_hash: bytes = noise.get_handshake_hash()
        self._buffer = bytearray(pending)
        self.closed = False

    def send(self, data: bytes) -> None:
        records = []
        for start in range(0, len(data), CHUNK):
            sealed = self.noise.encrypt(data[start:start + CHUNK])
            records.append(RECORD.pack(len(sealed)))
            records.append(sealed)
        self.raw.send(b"".join(records))

    def receive(self, max_bytes: int, timeout: float) -> bytes | None:
        plain = self._drain()
        if plain:
            return plain
        data = self.raw.receive(max(max_bytes, RECORD_MAX + RECORD.size), timeout)
        if not data:
            return data
        self._buffer += data
        return self._drain() or None

    def _drain(self) -> bytes:
        out = []
        buffer = self._buffer
        while len(buffer) >= RECORD.size:
            (size,) = RECORD.unpack_from(buffer)
            if len(buffer) < RECORD.size + size:
                break
            record = bytes(buffer[RECORD.size:RECORD.size + size])
            del buffer[:RECORD.size + size]
            try:
                out.append(self.noise.decrypt(record))
            except Exception:
                # the stream was altered, replayed or is not ours: it cannot go on
                raise OSError("a record on the secure stream does not verify") from None
        return b"".join(out)

    def close(self) -> None:
        self.closed = True
        self.raw.close()

    def address_gone(self) -> bool:
        gone = getattr(self.raw, "address_gone", None)
        return gone is not None and bool(gone())


def hkdf(secret: bytes, info: bytes, salt: bytes | None = None, length: int = 32) -> bytes:
    return HKDF(algorithm=SHA256(), length=length, salt=salt, info=info).derive(secret)


class KeySchedule(Changes):
    """A session's keys on one side. ``install`` each handshake's secret; routes ask for keys
    by epoch (``key id << 24 | generation``)."""

    def __init__(self, rekey: float, clock: Callable[[], float] = time.monotonic):
        self.rekey = rekey
        self.clock = clock
        self._lock = threading.Lock()
        # key id -> (root, generation 0 started at, erase at (None: current))
        self._roots: dict[int, tuple[bytes, float, float | None]] = {}
        self._sealing = -1  # the key id sealing now; key ids are 0..255, so -1 is none
        # read on every frame without the lock: (key id, its start) of the sealing root, and a
        # count of changes that makes every cached key be looked up again (a server that
        # restarted may reuse a key id: same epoch, another root)
        self._seal_state: tuple[int, float] | None = None
        self.version = 0
        self.offered: int | None = None  # the key id of the last secret this side offered

    def _changed(self) -> None:
        """Under the lock, after the roots or the sealing root changed."""
        found = self._roots.get(self._sealing)
        self._seal_state = (self._sealing, found[1]) if found else None
        self.version += 1

    def install(self, key_id: int, secret: bytes, handshake_hash: bytes,
                seal_now: bool = True) -> None:
        """A new root from a handshake. ``seal_now`` False: keep sealing under the previous
        root until :meth:`seal_with` (a server waits for the client to have the new one)."""
        root = hkdf(secret, b"rosgate/1 session root", salt=handshake_hash)
        now = self.clock()
        with self._lock:
            self._roots = {old: (r, started, now + GRACE)  # opens a while longer
                           for old, (r, started, _) in self._roots.items() if old != key_id}
            self._roots[key_id] = (root, now, None)
            if seal_now or self._sealing not in self._roots:
                self._sealing = key_id
            self._changed()

    def seal_with(self, key_id: object) -> None:
        """Seal under ``key_id`` from now on (the initiator says it holds it: ``ready``)."""
        with self._lock:
            if isinstance(key_id, int) and key_id in self._roots:
                self._sealing = key_id
                self._changed()

    def offer(self, handshake_hash: bytes) -> dict[str, Any]:
        """The responder's side: a fresh secret for this handshake, installed here, and what to
        send inside it. The previous root still seals until the initiator is ready."""
        first = self.offered is None
        # a random first id: a restarted server rarely reuses its predecessor's (and when it
        # does, the client's root serials keep the two apart)
        self.offered = os.urandom(1)[0] if self.offered is None else (self.offered + 1) % 256
        secret = os.urandom(32)
        self.install(self.offered, secret, handshake_hash, seal_now=first)
        return {"secret": secret.hex(), "key_id": self.offered, "rekey": self.rekey}

    def accept(self, offer: dict[str, Any], handshake_hash: bytes) -> int:
        """The initiator's side: install the secret of a responder's :meth:`offer`; its key id.
        ValueError (or KeyError, TypeError) when the offer holds none."""
        secret, key_id = bytes.fromhex(offer["secret"]), int(offer["key_id"])
        if len(secret) != 32 or not 0 <= key_id < 256:
            raise ValueError("not a session secret")
        self.install(key_id, secret, handshake_hash)
        return key_id

    def forget(self) -> None:
        """Erase every root (the session ends)."""
        with self._lock:
            self._roots.clear()
            self._sealing = -1
            self._changed()

    def epoch(self) -> int:
        state = self._seal_state
        if state is None:
            raise NoKey("no session key yet")
        return state[0] << 24 | self._generation(state[1])

    def _generation(self, started: float) -> int:
        return int((self.clock() - started) / self.rekey) % GENERATIONS

    def secret(self, epoch: int, label: str, size: int,
               sealing: bool) -> tuple[bytes, float] | None:
        """The key of ``label`` in ``epoch``, and until when (monotonic) it may be used without
        asking again (while :attr:`version` stays); None when this side no longer (or never)
        has it. Opening accepts the generation before and after our own; sealing any of a
        known root (a reply seals under its request's)."""
        key_id, generation = epoch >> 24, epoch % GENERATIONS
        now = self.clock()
        with self._lock:
            found = self._roots.get(key_id)
            if found is None:
                return None
            root, started, erase_at = found
            if erase_at is not None and now > erase_at:
                del self._roots[key_id]
                self._changed()
                return None
        until = erase_at if erase_at is not None else float("inf")
        if not sealing:
            if abs(generation - self._generation(started)) > 1:
                return None
            until = min(until, started + (generation + 2) * self.rekey)
        info = f"rosgate/1 {label} {generation}".encode()
        return hkdf(root, info, length=size), until


class SessionKeys(Keys):
    """A route's ciphers in a session: the entry's cipher class keyed per epoch, with
    ``send`` and ``receive`` labels (``topic c2s /robot1/scan``)."""

    #: ciphers kept per route: the generations either side of the current, across a handshake
    CACHE = 8

    def __init__(self, schedule: KeySchedule, cipher_cls: type[Cipher], send: str, receive: str):
        self.schedule = schedule
        self.cipher_cls = cipher_cls
        self.send_label = send
        self.receive_label = receive
        self.authenticates = cipher_cls.authenticates
        self.changes = schedule
        self.clock = schedule.clock
        # a keyless cipher (none) reads no file: any folder will do
        self._plain = cipher_cls({}, Path(".")) if cipher_cls.session_key_size == 0 else None
        # (epoch, sealing) -> (the schedule's version, usable until, cipher)
        self._cache: dict[tuple[int, bool], tuple[int, float, Cipher]] = {}
        self._lock = threading.Lock()

    def epoch(self) -> int:
        return self.schedule.epoch()

    def sealer(self, epoch: int) -> Cipher:
        cipher = self._cipher(epoch, True)
        if cipher is None:
            raise NoKey(f"no session key for epoch {epoch:#x}")
        return cipher

    def opener(self, epoch: int) -> Cipher | None:
        return self._cipher(epoch, False)

    def sealing(self) -> tuple[int, Cipher, float]:
        schedule = self.schedule
        state = schedule._seal_state
        if state is None:
            raise NoKey("no session key yet")
        age = int((schedule.clock() - state[1]) / schedule.rekey)
        epoch = state[0] << 24 | age % GENERATIONS
        found = self._held(epoch, True)
        if found is None:
            raise NoKey(f"no session key for epoch {epoch:#x}")
        return epoch, found[0], min(found[1], state[1] + (age + 1) * schedule.rekey)

    def opening(self, epoch: int) -> tuple[Cipher, float] | None:
        return self._held(epoch, False)

    def _cipher(self, epoch: int, sealing: bool) -> Cipher | None:
        found = self._held(epoch, sealing)
        return None if found is None else found[0]

    def _held(self, epoch: int, sealing: bool) -> tuple[Cipher, float] | None:
        """The cipher of ``epoch`` and until when it may be used while the schedule's version
        stays."""
        if self._plain is not None:  # `none`, where the policy allows it: nothing to key
            return self._plain, float("inf")
        key = (epoch, sealing)
        schedule = self.schedule
        cached = self._cache.get(key)
        if (cached is not None and cached[0] == schedule.version
                and schedule.clock() < cached[1]):
            return cached[2], cached[1]
        version = schedule.version
        label = self.send_label if sealing else self.receive_label
        found = schedule.secret(epoch, label, self.cipher_cls.session_key_size, sealing)
        if found is None:
            return None
        secret, until = found
        cipher = self.cipher_cls.from_secret(secret)
        with self._lock:
            if len(self._cache) >= self.CACHE:
                del self._cache[next(iter(self._cache))]
            self._cache[key] = (version, until, cipher)
        return cipher, until


def seal_hello(schedule: KeySchedule, session: int, seq: int) -> bytes:
    """A datagram that tells the server where this client's link is, sealed in the session."""
    epoch = schedule.epoch()
    header = envelope.pack(envelope.FLAG_HELLO, session, epoch, seq, time.time_ns())
    found = schedule.secret(epoch, HELLO_LABEL, 32, sealing=True)
    assert found is not None
    return header + ChaCha20Poly1305(found[0]).encrypt(header[8:20], b"", header)


def open_hello(schedule: KeySchedule, header: envelope.Header, frame: bytes) -> bool:
    """Whether a hello datagram was sealed in this session (not whether it is new)."""
    found = schedule.secret(header.epoch, HELLO_LABEL, 32, sealing=False)
    if found is None:
        return False
    try:
        ChaCha20Poly1305(found[0]).decrypt(frame[8:20], frame[envelope.SIZE:],
                                           frame[:envelope.SIZE])
    except InvalidTag:
        return False
    return True
