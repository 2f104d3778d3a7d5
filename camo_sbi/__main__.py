"""``python -m camo_sbi`` is the ``camo-sbi`` command (`camo_sbi.experiments.cli.console_main`)."""

import sys

from camo_sbi.experiments.cli import console_main

if __name__ == "__main__":
    sys.exit(console_main())
