"""The benchmark's plots (matplotlib, Agg backend, PNG).

* ``rates-SIZE.png``, one per size: offered against delivered msg/s, every trial of the
  sustained-rate search as a point (delivered = arrived by the trial's end + grace), the
  sustained trial ringed, the 2x-sustained overload trial as a cross, and the line y = x: a
  path that keeps up sits on it, one that saturates bends away flat.
* ``latency.png``: p50 / p90 / p99 one-way latency of every path at the latency trial's fixed
  rate, one panel per size (log scale: 1 MB and 100 B differ by a hundredfold).
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from pathlib import Path
from typing import Protocol

from processes import Route


class Trial(Protocol):
    """What is drawn of a trial (bench.Trial): its rate and what arrived, its latency."""
    rate: float
    sent: int
    p50_us: float | None
    p90_us: float | None
    p99_us: float | None

    @property
    def offered(self) -> float: ...

    @property
    def delivered(self) -> float: ...


class Size(Hashable, Protocol):
    name: str


class Result(Protocol):
    """What is drawn of a case (bench.Result): plots depend on this shape, not on bench.py,
    which imports them."""
    size: Size
    route: Route | None
    sustained: Trial | None
    latency: Trial | None
    overload: Trial | None

    @property
    def trials(self) -> Sequence[Trial]: ...

    @property
    def path(self) -> str: ...


def draw(results: list[Result], folder: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    rates = FuncFormatter(lambda v, _: f"{v / 1000:g}k" if v >= 1000 else f"{v:g}")

    folder.mkdir(parents=True, exist_ok=True)
    # one colour per path, the same for a base revision's row of it (dashed, hollow markers);
    # the default file's rows drawn heavier: they are the headline
    pairs = plt.get_cmap("tab20").colors  # ten colours, each with a light one: the strong first
    palette = pairs[::2] + pairs[1::2]
    colors: dict[str, tuple] = {}
    for r in results:
        colors.setdefault(kind(r), palette[len(colors) % len(palette)])
    sizes = list(dict.fromkeys(r.size for r in results))
    written = []

    for size in sizes:
        rows = [r for r in results if r.size == size and r.trials]
        if not rows:
            continue
        fig, ax = plt.subplots(figsize=(8, 6))
        low, high = float("inf"), 0.0
        for r in rows:
            color = colors[kind(r)]
            points = sorted((t.offered, t.delivered) for t in r.trials if t.sent)
            xs, ys = zip(*points, strict=True)
            base = bool(r.route and r.route.rev)
            ax.plot(xs, ys, "o--" if base else "o-", color=color, label=r.path, markersize=5,
                    markerfacecolor="none" if base else color,
                    linewidth=1.8 if r.route and r.route.default_file else 0.8, alpha=0.85)
            if r.sustained:
                ax.plot([r.sustained.offered], [r.sustained.delivered], "o", markersize=12,
                        markerfacecolor="none", markeredgecolor=color)
            if r.overload and r.overload.sent:
                ax.plot([r.overload.offered], [r.overload.delivered], "x", color=color,
                        markersize=9, markeredgewidth=2)
                xs, ys = (*xs, r.overload.offered), (*ys, r.overload.delivered)
            low = min(low, *xs, *(y for y in ys if y > 0))
            high = max(high, *xs, *ys)
        if high <= 0:
            plt.close(fig)
            continue
        line = [low / 1.5, high * 1.5]
        ax.plot(line, line, "--", color="grey", linewidth=1, label="delivered = offered")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlim(*line)
        ax.set_ylim(line[0], line[1])
        for axis in (ax.xaxis, ax.yaxis):
            axis.set_major_formatter(rates)
            axis.set_minor_formatter(rates if high / low < 30 else FuncFormatter(lambda *_: ""))
        ax.set_xlabel("offered msg/s (publisher)")
        ax.set_ylabel("delivered msg/s (arrived by the trial's end + grace)")
        ax.set_title(f"{size.name}: offered vs delivered, every trial "
                     "(ring: sustained, x: 2x sustained)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8, loc="upper left")
        fig.tight_layout()
        path = folder / f"rates-{size.name.replace(' ', '')}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)

    panels = [(size, [r for r in results if r.size == size and r.latency and r.latency.p50_us])
              for size in sizes]
    panels = [(size, rows) for size, rows in panels if rows]
    if panels:
        height = sum(1.2 + 0.45 * len(rows) for _, rows in panels)
        fig, axes = plt.subplots(len(panels), 1, figsize=(8, height), squeeze=False)
        for ax, (size, rows) in zip(axes[:, 0], panels, strict=True):
            labels = [r.path for r in rows][::-1]
            rows = rows[::-1]
            for i, (q, shade) in enumerate((("p50_us", 1.0), ("p90_us", 0.65), ("p99_us", 0.35))):
                values = [(getattr(r.latency, q) or 0) / 1000 for r in rows]
                ys = [y + (1 - i) * 0.27 for y in range(len(rows))]
                ax.barh(ys, values, height=0.27, color=[colors[kind(r)] for r in rows],
                        alpha=shade)
                for y, value in zip(ys, values, strict=True):
                    ax.text(value, y, f" {q[:3]} {value:.2f}", va="center", fontsize=7)
            ax.margins(x=0.25)
            ax.set_yticks(range(len(rows)), labels, fontsize=8)
            ax.set_xscale("log")
            shown = [v for r in rows for v in (r.latency.p50_us, r.latency.p99_us) if v]
            narrow = max(shown) / min(shown) < 10  # no decade tick inside: label the minor ones
            plain = FuncFormatter(lambda v, _: f"{v:g}")
            ax.xaxis.set_major_formatter(plain)
            ax.xaxis.set_minor_formatter(plain if narrow else FuncFormatter(lambda *_: ""))
            ax.tick_params(axis="x", which="minor", labelsize=7)
            ax.set_xlabel("one-way latency, ms (log scale)", fontsize=8)
            rate = rows[0].latency.rate
            ax.set_title(f"{size.name} at {rate:,.0f} msg/s", fontsize=10)
            ax.grid(True, axis="x", which="both", alpha=0.3)
        fig.tight_layout()
        path = folder / "latency.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)
    return written


def kind(result: Result) -> str:
    """A row's path without the revision: what its colour follows."""
    return result.route.path if result.route else "bare rclpy"
