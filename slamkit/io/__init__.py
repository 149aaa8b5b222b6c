"""Dataset readers and trajectory I/O. Every reader yields ``slamkit.sensors.FrameData``."""
