"""Which cipher seals and opens a route's frames, by the envelope's epoch.

A route asks its :class:`Keys` for the epoch to seal under now, and for the cipher of an epoch
a frame names. :class:`StaticKeys` is one cipher built from the file's options (peer role, and
``insecure: true``) with a random epoch per sender start. A session's keys (``rosgate.secure``)
change with every key generation and every handshake, and the epoch says which.
"""

from __future__ import annotations

import os
from abc import ABC, abstractmethod

from .cipher import Cipher


class NoKey(LookupError):
    """There is no key to seal under yet (a session whose handshake has not happened)."""


class Keys(ABC):
    """The ciphers of one route."""

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
