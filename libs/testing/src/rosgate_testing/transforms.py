"""The conformance suite of payload transforms (:mod:`rosgate.transform`)::

    from rosgate_testing import TransformConformance

    class TestZstdConformance(TransformConformance):
        transform = ZstdTransform
        options = {"level": 19}          # its table, as under plugins: (default {})

It checks: the class is found through its entry point; payloads from empty to 1 MiB (text,
zeros, noise) come back byte for byte, or are left as they are (``encode`` returns None); a
compressing transform (``compresses = True``, the default) shrinks what repeats; ``decode``
refuses what would be over its ``limit`` with :class:`rosgate.TransformError`; seeded garbage and
damaged encodings are a result within the limit or ``TransformError``, never another exception;
one instance encodes and decodes from several threads at once.
"""

from __future__ import annotations

import itertools
import random
import threading
from collections.abc import Mapping
from typing import Any, ClassVar

import pytest

from rosgate import Transform, TransformError
from rosgate.options import parse

from .helpers import assert_registered, mutations

LIMIT = 4 * 1024 * 1024


def payloads() -> dict[str, bytes]:
    rng = random.Random(7)
    text = b"".join(b"topic /robot%d/odom, frame %d; " % (i % 7, i) for i in range(3000))
    return {"empty": b"", "one byte": b"x", "short text": b"hello, world", "text": text,
            "zeros": bytes(1 << 20), "noise": rng.randbytes(50_000),
            "mixed": text[:20_000] + rng.randbytes(20_000) + bytes(20_000)}


class TransformConformance:
    """Subclass it as ``Test...`` and set :attr:`transform`."""

    transform: ClassVar[type[Transform]]
    options: ClassVar[Mapping[str, Any]] = {}
    #: a compressor: a payload that repeats comes back smaller
    compresses: ClassVar[bool] = True
    fuzz_inputs: ClassVar[int] = 400

    def make(self, limit: int = LIMIT) -> Transform:
        """An instance made from :attr:`options` as the core makes it."""
        return self.transform(parse(self.transform, self.options), limit)

    def test_found_through_its_entry_point(self) -> None:
        assert_registered("transform", self.transform)

    @pytest.mark.parametrize("name", list(payloads()))
    def test_round_trip(self, name: str) -> None:
        payload = payloads()[name]
        transform = self.make()
        packed = transform.encode(payload)
        if packed is None:  # sent as it was
            return
        assert isinstance(packed, bytes)
        assert transform.decode(packed) == payload
        assert self.make().decode(packed) == payload  # another instance: nothing kept between

    def test_what_repeats_gets_smaller(self) -> None:
        if not self.compresses:
            pytest.skip(f"{self.transform.name} does not compress (compresses = False)")
        payload = payloads()["text"]
        packed = self.make().encode(payload)
        assert packed is not None and len(packed) < len(payload) // 2

    def test_decode_refuses_a_result_over_its_limit(self) -> None:
        payload = payloads()["zeros"]
        packed = self.make().encode(payload)
        if packed is None:
            pytest.skip(f"{self.transform.name} left 1 MiB of zeros as it was")
        with pytest.raises(TransformError):
            self.make(limit=len(payload) - 1).decode(packed)

    def test_garbage_is_a_transform_error_and_nothing_else(self) -> None:
        rng = random.Random(20240601)
        transform = self.make(limit=1 << 20)
        valid = [p for p in (transform.encode(payloads()[n]) for n in ("text", "mixed")) if p]
        inputs = itertools.chain(
            (rng.randbytes(rng.randrange(64)) for _ in range(self.fuzz_inputs // 2)),
            *(mutations(v, rng, self.fuzz_inputs // (2 * len(valid))) for v in valid))
        for data in inputs:
            try:
                result = transform.decode(data)
            except TransformError:
                continue
            except Exception as exc:  # the point of the test: report, do not propagate
                pytest.fail(f"decode({data[:40]!r}...) raised {type(exc).__name__}: {exc}")
            assert isinstance(result, bytes) and len(result) <= 1 << 20

    def test_one_instance_serves_several_threads_at_once(self) -> None:
        transform = self.make()
        rng = random.Random(3)
        work = [payloads()["text"][rng.randrange(1000):] for _ in range(64)]
        failures: list[str] = []

        def run(items: list[bytes]) -> None:
            for payload in items:
                packed = transform.encode(payload)
                if packed is not None and transform.decode(packed) != payload:
                    failures.append(f"{len(payload)} bytes did not come back")

        threads = [threading.Thread(target=run, args=(work[i::4],)) for i in range(4)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(30)
        assert failures == []
