"""Ctrl-C in a child ``slamkit run``: the Ctrl-C tests of the threaded runner and of the live camera."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Sequence

import pytest


def interrupt_after(cmd: Sequence[str], marker: str, delay_s: float, timeout_s: float = 120.0) -> tuple[int, str]:
    """Start ``cmd``, wait for the output line holding ``marker``, ``delay_s`` more, then send SIGINT; returns the
    exit code and the whole output (stdout and stderr). Fails the test when the child does not end within
    ``timeout_s`` of the signal."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    # Ctrl-C's default action in the child even when this test runs as a background job (a non-interactive
    # shell starts those with SIGINT ignored, the child would inherit that and Python would not raise
    # KeyboardInterrupt at all)
    proc = subprocess.Popen(
        list(cmd),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    assert proc.stdout is not None
    lines = []
    for line in proc.stdout:
        lines.append(line)
        if marker in line:
            break
    time.sleep(delay_s)
    proc.send_signal(signal.SIGINT)
    try:
        rest, _ = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        pytest.fail(f"the run did not stop within {timeout_s:.0f} s of Ctrl-C:\n" + "".join(lines))
    return proc.returncode, "".join(lines) + rest
