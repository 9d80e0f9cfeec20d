"""``python -m rosgate_emulator udp|tcp ...``: a relay as a process of its own."""

import sys

from .cli import main

sys.exit(main())
