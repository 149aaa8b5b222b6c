"""``python -m slamkit`` is the ``slamkit`` command."""

import sys

from slamkit.cli import main

sys.exit(main())
