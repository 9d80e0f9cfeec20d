"""The :class:`Lifetime` that closes what a bridge has open when it stops."""

from __future__ import annotations

import threading
from typing import Any

from .base import Link


class Lifetime:
    """What a running bridge closes when it stops, in reverse opening order (links that end by
    themselves are forgotten), and the event that says it is stopping."""

    def __init__(self) -> None:
        self.stopping = threading.Event()
        self._items: dict[int, Any] = {}
        self._lock = threading.Lock()

    def closing(self, item: Any) -> Any:
        with self._lock:
            self._items[id(item)] = item
        return item

    def forget(self, item: Any) -> None:
        with self._lock:
            self._items.pop(id(item), None)

    def links(self) -> list[Link]:
        """The links open now that count what they carry."""
        with self._lock:
            return [item for item in self._items.values() if isinstance(item, Link)]

    def close_all(self) -> None:
        self.stopping.set()
        with self._lock:
            items = list(self._items.values())
            self._items.clear()
        for item in reversed(items):
            item.close()
