"""Run one fuzz target under atheris (coverage-guided, libFuzzer's engine):

    python tests/fuzz/fuzz.py TARGET [libFuzzer flags] [corpus directories]

Every rosgate module a target reaches is instrumented for coverage. An input is a finding when
the target raises, when it takes more than ``ROSGATE_FUZZ_LIMIT_MS`` (default 100) ms of CPU, or
when the process outgrows libFuzzer's ``-rss_limit_mb``. ``campaign.py`` runs every target.
"""

from __future__ import annotations

import gc
import os
import sys
import time
from pathlib import Path

import atheris

sys.path.insert(0, str(Path(__file__).parent))

with atheris.instrument_imports(include=["rosgate", "rosgate_message_tree", "rosgate_mcu_cvra",
                                         "rosgate_codec_msgpack", "rosgate_codec_cbor",
                                         "targets"]):
    import rosgate_codec_cbor  # noqa: F401
    import rosgate_codec_msgpack  # noqa: F401
    import rosgate_mcu_cvra  # noqa: F401
    import rosgate_message_tree  # noqa: F401
    import targets

    import rosgate.config
    import rosgate.roles.mainline
    import rosgate.ros  # noqa: F401
    from rosgate.wire import control, envelope, framing, names  # noqa: F401

LIMIT = float(os.environ.get("ROSGATE_FUZZ_LIMIT_MS", "100")) / 1000


class TooSlow(Exception):
    """An input that took longer than the limit: a finding like a crash."""


def main() -> None:
    name = sys.argv.pop(1)
    run = targets.TARGETS[name]
    # no warm-up: code run before atheris.Fuzz() is not seen as coverage (measured: the cdr
    # target's 93 edges became 20). What the first inputs build (a message type's converters,
    # its type support) is exempt from the time limit instead.
    gc.collect()
    gc.freeze()  # what setup made is never collected: a collection stays short

    def one(data: bytes) -> None:
        built, start = targets.caches(), time.thread_time()
        run(data)
        spent = time.thread_time() - start
        if spent > LIMIT and targets.caches() == built:
            raise TooSlow(f"{name}: {spent * 1000:.0f} ms of CPU for {len(data)} bytes")

    atheris.Setup(sys.argv, one)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
