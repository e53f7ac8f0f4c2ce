"""`torchfra bench` as a script (the same flags): ``python scripts/bench.py --help``."""
from torchfra.cli.bench import main
from torchfra.cli.run import run

if __name__ == "__main__":
    run(main)
