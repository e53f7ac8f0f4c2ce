"""The allocator setting of the commands (torchfra.runtime.allocator): on Linux with glibc it is in force in a
command's process (``torchfra.cli.run.run``), ``TORCHFRA_MALLOC=default`` leaves the allocator alone, and
importing torchfra changes nothing in the host process."""
import os
import subprocess
import sys

import pytest

IMPORT = "import torchfra.runtime.allocator as a, torchfra.fem; print(a.state['tuned'], a.state['reason'])"
COMMAND = ("import torchfra.runtime.allocator as a; from torchfra.cli.run import run; "
           "run(lambda: print(a.state['tuned'], a.state['reason']))")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt exists on Linux only")
def test_a_command_keeps_freed_memory_unless_told_not_to_and_an_import_leaves_the_process_alone():
    env = {k: v for k, v in os.environ.items() if k != "TORCHFRA_MALLOC"}
    imported = subprocess.run([sys.executable, "-c", IMPORT], capture_output=True, text=True, check=True, env=env).stdout
    assert imported.split()[0] == "False", imported
    tuned = subprocess.run([sys.executable, "-c", COMMAND], capture_output=True, text=True, check=True, env=env).stdout
    assert tuned.split()[0] == "True", tuned
    left = subprocess.run([sys.executable, "-c", COMMAND], capture_output=True, text=True, check=True,
                          env=dict(env, TORCHFRA_MALLOC="default")).stdout
    assert left.split()[0] == "False" and "TORCHFRA_MALLOC" in left, left
