"""The allocator setting made at import (torchfra.runtime.allocator): on Linux with glibc it is in force after
``import torchfra``, and ``TORCHFRA_MALLOC=default`` leaves the allocator alone."""
import os
import subprocess
import sys

import pytest

PROBE = "import torchfra.runtime.allocator as a, torchfra; print(a.state['tuned'], a.state['reason'])"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt exists on Linux only")
def test_import_keeps_freed_memory_unless_told_not_to():
    tuned = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, check=True).stdout
    assert tuned.split()[0] == "True", tuned
    env = dict(os.environ, TORCHFRA_MALLOC="default")
    left = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, check=True, env=env).stdout
    assert left.split()[0] == "False" and "TORCHFRA_MALLOC" in left, left
