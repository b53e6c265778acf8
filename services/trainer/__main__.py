"""The trainer service's entry point: ``python -m services.trainer train|eval|bench|models ...``.

It is the ``neuro`` command; the trainer runs as a batch job that writes the artifact registry
that the emulator and controller services read.
"""

from __future__ import annotations

import sys

from neuroanimator.cli import main

if __name__ == "__main__":
    sys.exit(main())
