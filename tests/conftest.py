import os

# MKL (PARDISO) runs one thread per test process, as torch does: with a worker per core
# (pytest-xdist, pyproject's addopts) more would only oversubscribe the cores. Set before MKL loads.
os.environ.setdefault("MKL_NUM_THREADS", "1")

import torch  # noqa: E402

from torchfra.runtime.allocator import keep_freed_memory  # noqa: E402

# the test processes run FE solves as the commands do, with the commands' allocator setting
keep_freed_memory()

# Threads are set explicitly (DESIGN §5): torch.func code ran 10-20x slower with 2 threads on a
# loaded 2-core machine. Override with TORCHFRA_THREADS.
torch.set_num_threads(int(os.environ.get("TORCHFRA_THREADS", "1")))
torch.set_default_dtype(torch.float64)

MAX_WORKERS = 4  # each worker holds its own FE models and caches in memory


def pytest_xdist_auto_num_workers(config):
    """``-n auto``: one worker per core, at most MAX_WORKERS (PYTEST_XDIST_AUTO_NUM_WORKERS overrides)."""
    return max(1, min(os.cpu_count() or 1, MAX_WORKERS))
