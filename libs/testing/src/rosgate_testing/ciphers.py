"""The conformance suite of ciphers."""

from __future__ import annotations

import itertools
import random
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar

import pytest

from rosgate import Cipher, CipherError
from rosgate.options import parse
from rosgate.wire import envelope

from .helpers import assert_registered, write_key

HEADER = envelope.pack(0, 7, 0xCAFE, 1, 1_700_000_000_000_000_000)


class CipherConformance:
    """The conformance suite of a cipher. Set :attr:`cipher`; override :meth:`options_for`
    for a cipher whose key does not come from ``key_file``."""

    #: the Cipher subclass under test
    cipher: ClassVar[type[Cipher]]

    def options_for(self, key_file: Path) -> dict[str, Any]:
        """The options naming the key written to ``key_file`` (in the base directory)."""
        return {"key_file": key_file.name}

    @pytest.fixture
    def make_cipher(self, tmp_path: Path) -> Callable[[bytes | None], Cipher]:
        """Build the cipher under ``key`` (None: keyless), as a bridge would from its file."""
        files = itertools.count()

        def make(key: bytes | None) -> Cipher:
            if key is None:
                return self.cipher(parse(self.cipher, {}), tmp_path)
            path = write_key(tmp_path / f"{self.cipher.name}-{next(files)}.key", key)
            return self.cipher(parse(self.cipher, self.options_for(path)), tmp_path)
        return make

    @pytest.fixture
    def pair(self, make_cipher) -> tuple[Cipher, Cipher]:
        """Two instances under one key: the two sides of a link."""
        key = self.cipher.generate_key()
        return make_cipher(key), make_cipher(key)

    # Which tests a cipher gets depends on what it declares: the tamper tests for ciphers that
    # authenticate, and for one that does not (like ``none``) a check that it says so honestly.
    AUTHENTICATION_TESTS = (
        "test_every_flipped_bit_of_the_body_is_refused",
        "test_every_flipped_bit_of_the_header_is_refused", "test_another_key_is_refused",
        "test_every_truncation_is_refused", "test_garbage_is_a_cipher_error_and_nothing_else",
        "test_two_seals_of_one_payload_differ")

    def __init_subclass__(cls, **kwargs: object) -> None:
        super().__init_subclass__(**kwargs)
        cipher = getattr(cls, "cipher", None)
        if cipher is None:
            return
        drop = cls.AUTHENTICATION_TESTS if not cipher.authenticates else (
            "test_a_cipher_that_does_not_authenticate_says_so",)
        for name in drop:
            setattr(cls, name, None)  # pytest collects only callables

    def test_a_cipher_that_does_not_authenticate_says_so(self, pair) -> None:
        """``authenticates = False`` must be true: a tampered body is not refused."""
        sealer, opener = pair
        body = bytearray(sealer.seal(HEADER, b"the payload"))
        body[-1] ^= 1
        opener.open(HEADER, bytes(body))

    def test_found_through_its_entry_point(self) -> None:
        assert_registered("cipher", self.cipher)

    def test_generate_key(self) -> None:
        first = self.cipher.generate_key()
        if first is None:
            return  # keyless
        assert isinstance(first, bytes) and first == first.strip()
        assert self.cipher.generate_key() != first

    @pytest.mark.parametrize("size", [0, 1, 28, 2500, 1 << 20])
    def test_round_trip(self, pair, size: int) -> None:
        sealer, opener = pair
        payload = random.Random(size).randbytes(size)
        body = sealer.seal(HEADER, payload)
        assert isinstance(body, bytes)
        assert opener.open(HEADER, body) == payload
        assert sealer.open(HEADER, body) == payload

    def test_every_flipped_bit_of_the_body_is_refused(self, pair) -> None:
        """Allowed: a flip that opens to the very same payload, all in one byte (an encoding's
        spare bits, as in the padding of Fernet's base64). Never a different payload."""
        sealer, opener = pair
        payload = b"the payload"
        body = sealer.seal(HEADER, payload)
        accepted_at = set()
        for i in range(len(body)):
            for bit in range(8):
                tampered = bytearray(body)
                tampered[i] ^= 1 << bit
                try:
                    opened = opener.open(HEADER, bytes(tampered))
                except CipherError:
                    continue
                assert opened == payload, f"bit {bit} of byte {i} flipped opened to {opened!r}"
                accepted_at.add(i)
        assert len(accepted_at) <= 1, f"flips at bytes {sorted(accepted_at)} were accepted"

    def test_every_flipped_bit_of_the_header_is_refused(self, pair) -> None:
        sealer, opener = pair
        body = sealer.seal(HEADER, b"the payload")
        for i in range(len(HEADER)):
            for bit in range(8):
                other = bytearray(HEADER)
                other[i] ^= 1 << bit
                with pytest.raises(CipherError):
                    opener.open(bytes(other), body)

    def test_another_key_is_refused(self, pair, make_cipher) -> None:
        sealer, _ = pair
        stranger = make_cipher(self.cipher.generate_key())
        with pytest.raises(CipherError):
            stranger.open(HEADER, sealer.seal(HEADER, b"secret"))

    def test_every_truncation_is_refused(self, pair) -> None:
        sealer, opener = pair
        body = sealer.seal(HEADER, b"x" * 40)
        for length in range(len(body)):
            with pytest.raises(CipherError):
                opener.open(HEADER, body[:length])

    def test_garbage_is_a_cipher_error_and_nothing_else(self, pair) -> None:
        _, opener = pair
        rng = random.Random(11)
        for _ in range(500):
            body = rng.randbytes(rng.randrange(300))
            try:
                opener.open(HEADER, body)
            except CipherError:
                continue
            except Exception as exc:  # the point of the test: report, do not propagate
                pytest.fail(f"open({body!r}) raised {type(exc).__name__}: {exc}")
            pytest.fail(f"open accepted random bytes {body!r}")

    def test_keyed_from_a_session_secret(self) -> None:
        """A cipher that declares ``session_key_size`` is keyed by :meth:`Cipher.from_secret`:
        two instances of one secret talk, another secret or a changed header is refused, and
        sealing under the sequence numbers of a session (unique per key) round-trips."""
        import os

        size = self.cipher.session_key_size
        if not size:
            return  # cannot be keyed from a session (refused there unless a policy allows it)
        secret = os.urandom(size)
        sealer, opener = self.cipher.from_secret(secret), self.cipher.from_secret(secret)
        for seq in (1, 2, 2**40):
            header = envelope.pack(0, 7, 3 << 24 | 5, seq, 0)
            assert opener.open(header, sealer.seal(header, b"payload %d" % seq)) \
                == b"payload %d" % seq
        header = envelope.pack(0, 7, 1, 1, 0)
        body = sealer.seal(header, b"x")
        with pytest.raises(CipherError):
            self.cipher.from_secret(os.urandom(size)).open(header, body)
        with pytest.raises(CipherError):
            opener.open(envelope.pack(0, 7, 1, 2, 0), body)

    def test_two_seals_of_one_payload_differ(self, pair) -> None:
        """A fresh nonce (or IV) per frame: equal payloads must not be seen to be equal."""
        sealer, _ = pair
        assert sealer.seal(HEADER, b"same") != sealer.seal(HEADER, b"same")
