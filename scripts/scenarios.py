"""`torchfra scenarios` as a script (the same flags): ``python scripts/scenarios.py --help``."""
from torchfra.cli.run import run
from torchfra.cli.scenarios import main

if __name__ == "__main__":
    run(main)
