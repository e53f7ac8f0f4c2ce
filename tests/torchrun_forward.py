"""Run by tests/test_distributed.py under torchrun: scripts/forward_uq.py with each rank's own run
folder (<base>/rank<R>), as ranks on machines that share no file system would have."""
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
sys.path.insert(0, str(ROOT))

import forward_uq  # noqa: E402

if __name__ == "__main__":
    base, args = sys.argv[1], sys.argv[2:]
    forward_uq.main(args + ["--runs-dir", str(Path(base) / f"rank{os.environ.get('RANK', '0')}")])
