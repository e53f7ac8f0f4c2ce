"""`torchfra demo` as a script (the same flags): ``python scripts/fem_demo.py --help``."""
from torchfra.cli.demo import main
from torchfra.cli.run import run

if __name__ == "__main__":
    run(main)
