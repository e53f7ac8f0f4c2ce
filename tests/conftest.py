import os

import torch

# Threads are set explicitly (DESIGN §5): torch.func code ran 10-20x slower with 2 threads on a
# loaded 2-core machine. Override with TORCHFRA_THREADS.
torch.set_num_threads(int(os.environ.get("TORCHFRA_THREADS", "1")))
torch.set_default_dtype(torch.float64)
