"""Which cipher seals and opens a route's frames: :class:`StaticKeys`, one cipher from the file's
options (peer role, ``insecure: true``), or a session's keys (:mod:`rosgate.secure`), which
change with every key generation and handshake.
"""

from __future__ import annotations

import os
from abc import ABC, abstractmethod

from .cipher import Cipher


class NoKey(LookupError):
    """There is no key to seal under yet (a session whose handshake has not happened)."""


class Keys(ABC):
    """The ciphers of one route, by the envelope's epoch."""

    #: True when ``open`` proves a frame came from a key holder unchanged
    authenticates: bool = True

    @abstractmethod
    def epoch(self) -> int:
        """The epoch a frame sealed now carries; :class:`NoKey` when there is none yet."""

    @abstractmethod
    def sealer(self, epoch: int) -> Cipher:
        """The cipher that seals frames of ``epoch`` (a reply seals under its request's)."""

    @abstractmethod
    def opener(self, epoch: int) -> Cipher | None:
        """The cipher that opens frames of ``epoch``; None when no key of this route has it
        (an earlier session, a server restart, a generation long expired)."""


class StaticKeys(Keys):
    """One cipher for every epoch; the epoch only starts a new sequence at each sender start."""

    def __init__(self, cipher: Cipher):
        self.cipher = cipher
        self.authenticates = cipher.authenticates
        self._epoch = int.from_bytes(os.urandom(4), "big")

    def epoch(self) -> int:
        return self._epoch

    def sealer(self, epoch: int) -> Cipher:
        return self.cipher

    def opener(self, epoch: int) -> Cipher | None:
        return self.cipher
