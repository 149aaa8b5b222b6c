"""A plugin whose module fails to import (a dependency that is not installed)."""

import slamkit_dependency_that_does_not_exist  # noqa: F401
