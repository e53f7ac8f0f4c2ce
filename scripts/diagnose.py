"""`torchfra diagnose` as a script (the same flags): ``python scripts/diagnose.py --help``."""
from torchfra.cli.diagnose import main
from torchfra.cli.run import run

if __name__ == "__main__":
    run(main)
