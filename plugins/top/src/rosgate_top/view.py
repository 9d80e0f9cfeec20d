"""What ``rosgate top`` shows: two statuses of a bridge (:mod:`rosgate.status`) become rates,
and the rates become two tables (rich).

Every word of a status is shown as plain text (:func:`clean`): names and refusals carry what
clients and peers chose (an entry's name, a reason quoting it), so rich markup in them is shown
as written, never applied, and a terminal control character is shown as its escape
(``\x1b``), never sent to the terminal.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from rich.console import Group
from rich.table import Table
from rich.text import Text

#: what ``s`` cycles through: the column a table is sorted by
SORT_KEYS = ("name", "out/s", "in/s", "drops")
MAX_WORD = 300  # characters of one word shown; a longer one is cut


def clean(value: Any) -> Text:
    """``value`` as text to show: control and format characters (escapes, bidirectional
    overrides) written as their escapes, cut at :data:`MAX_WORD`, never read as markup."""
    text = str(value)[:MAX_WORD]
    if not text.isprintable():
        text = "".join(c if c.isprintable() else ascii(c)[1:-1] for c in text)
    return Text(text)


@dataclass
class Row:
    entry: dict[str, Any]
    out_rate: float | None  # messages per second
    in_rate: float | None
    out_bytes: float | None  # bytes per second
    in_bytes: float | None
    new_drops: dict[str, int]  # since the previous status

    def sort_value(self, key: str) -> Any:
        if key == "out/s":
            return self.out_rate or 0.0
        if key == "in/s":
            return self.in_rate or 0.0
        if key == "drops":
            return sum(self.entry["drops"].values())
        return self.entry["name"]


def _key(e: dict[str, Any]) -> tuple[Any, ...]:
    return e["kind"], e["name"], e["direction"], e["peer"]


def rows(now: dict[str, Any], before: dict[str, Any] | None) -> list[Row]:
    old = {_key(e): e for e in (before or {}).get("entries", [])}
    span = now["time"] - before["time"] if before else 0.0
    out = []
    for e in now["entries"]:
        o = old.get(_key(e))

        def rate(field: str, e: dict[str, Any] = e, o: dict[str, Any] | None = o) -> float | None:
            return (e[field] - o[field]) / span if o is not None and span > 0 else None
        new = {k: v - (o["drops"].get(k, 0) if o else 0) for k, v in e["drops"].items()}
        out.append(Row(e, rate("sent"), rate("received"), rate("bytes_sent"),
                       rate("bytes_received"), {k: v for k, v in new.items() if v > 0}))
    return out


def render(now: dict[str, Any], before: dict[str, Any] | None, sort: str = "name",
           reverse: bool = False, keys: bool = True) -> Group:
    """The whole view; ``keys``: with the line that says which keys do what."""
    parts: list[Any] = [_header(now), _entries(now, before, sort, reverse), _links(now, before)]
    if keys:
        parts.append(Text("s: sort by the next column   r: reverse   q: quit", style="dim"))
    return Group(*parts)


def _header(now: dict[str, Any]) -> Text:
    peers = ", ".join(f"{p['name']} {_state(p['up'])}" for p in now["peers"]) or "none"
    text = Text()
    text.append(clean(f"rosgate {now['bridge']}").plain, style="bold")
    text.append(clean(f" ({now['role']}), up {_duration(now['uptime'])}; peers: {peers}"))
    if now["link_drops"]:
        text.append(clean("; frames for no topic: " + _drops(now["link_drops"])).plain,
                    style="yellow")
    return text


def _entries(now: dict[str, Any], before: dict[str, Any] | None, sort: str,
             reverse: bool) -> Table:
    mark = " ▼" if not reverse else " ▲"
    table = Table(title="topics and services", title_justify="left", expand=False)
    for column in ("NAME", "KIND", "DIR", "PEER", "OUT/S", "IN/S", "OUT B/S", "IN B/S",
                   "LATENCY", "QUEUE", "STALE", "DROPS"):
        header = column + (mark if column.lower() == sort else "")
        table.add_column(header, justify="right" if "/S" in column or column in (
            "LATENCY", "QUEUE") else "left", no_wrap=column != "DROPS")
    ordered = sorted(rows(now, before), key=lambda r: r.sort_value(sort),
                     reverse=reverse != (sort != "name"))
    for r in ordered:
        e = r.entry
        name, kind, peer = _name(e), clean(e["kind"]), clean(e["peer"])
        if e["refused"] is not None:
            state = Text(clean(f"refused: {e['refused']}").plain, style="bold red")
            table.add_row(name, kind, _way(e["direction"]), peer, "", "", "", "",
                          "", "", "", state)
            continue
        drops = Text(clean(_drops(e["drops"]) or "-").plain,
                     style="bold red" if r.new_drops else "")
        stale = {True: Text("stale", style="yellow"), False: Text("no"), None: Text("-")}[
            e["stale"]]
        table.add_row(name, kind, _way(e["direction"]), peer,
                      _number(r.out_rate), _number(r.in_rate), _bytes(r.out_bytes),
                      _bytes(r.in_bytes), _seconds(e["latency"]), _queue(e), stale,
                      drops)
    return table


def _queue(e: dict[str, Any]) -> Text:
    """An entry's queue, and whether it sheds (its queue in the bridge stands behind)."""
    if e.get("shedding"):  # (a status from before the field has none)
        return Text(f"{clean(e['queue']).plain} shedding", style="yellow")
    return clean(e["queue"])


def _links(now: dict[str, Any], before: dict[str, Any] | None) -> Table:
    old = {link["name"]: link for link in (before or {}).get("links", [])}
    span = now["time"] - before["time"] if before else 0.0
    table = Table(title="links", title_justify="left")
    for column in ("LINK", "STATE", "RTT", "OUT B/S", "IN B/S", "BUDGET USE", "QUEUE"):
        table.add_column(column, justify="left" if column in ("LINK", "STATE") else "right",
                         no_wrap=True)
    for link in sorted(now["links"], key=lambda link: link["name"]):
        o = old.get(link["name"])
        out_rate = (link["bytes_out"] - o["bytes_out"]) / span if o and span > 0 else None
        in_rate = (link["bytes_in"] - o["bytes_in"]) / span if o and span > 0 else None
        budget = link["bandwidth"]
        use = (f"{out_rate * 8 / budget:.0%}" if budget and out_rate is not None
               else "-" if not budget else "")
        table.add_row(clean(link["name"]), Text(_state(link["up"]),
                                         style="green" if link["up"] else "bold red"),
                      _seconds(link["rtt"]), _bytes(out_rate), _bytes(in_rate), use,
                      clean(link["queue"]))
    return table


def _name(e: dict[str, Any]) -> Text:
    """An entry's name; a route a pattern made says which (``/r/scan (found by /r/**)``)."""
    name = clean(e["name"])
    if e.get("pattern"):  # a bridge older than the field has listed entries only
        name.append(clean(f" (found by {e['pattern']})").plain, style="dim")
    return name


def _way(direction: str | None) -> str:
    return {"transmit": "out", "receive": "in"}.get(direction or "", "?")


def _state(up: bool | None) -> str:
    return "up" if up is True else "DOWN" if up is False else "?"


def _drops(drops: dict[str, int]) -> str:
    return " ".join(f"{k}={v}" for k, v in sorted(drops.items()))


def _number(value: float | None) -> str:
    if value is None:
        return "…"
    return f"{value:.0f}" if value >= 10 else f"{value:.1f}"


def _bytes(value: float | None) -> str:
    if value is None:
        return "…"
    for unit in ("B", "kB", "MB"):
        if value < 1000:
            return f"{value:.0f} {unit}" if unit == "B" else f"{value:.1f} {unit}"
        value /= 1000
    return f"{value:.1f} GB"


def _seconds(value: float | None) -> str:
    return "-" if value is None else f"{value * 1000:.1f} ms"


def _duration(seconds: float) -> str:
    s = int(seconds)
    return f"{s // 3600:d}:{s // 60 % 60:02d}:{s % 60:02d}"
