"""`torchfra calibrate` as a script (the same flags): ``python scripts/calibrate.py --help``."""
from torchfra.cli.calibrate import main
from torchfra.cli.run import run

if __name__ == "__main__":
    run(main)
