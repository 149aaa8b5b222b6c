"""``python -m slamkit_dbow vocab train | convert | info | eval`` (the ``slamkit vocab`` command)."""

import sys

from slamkit_dbow.cli import main

sys.exit(main())
