"""An example third-party slamkit plugin, installed by the test suite as its own distribution."""
