"""`torchfra forward` as a script (the same flags): ``python scripts/forward_uq.py --help``."""
from torchfra.cli.forward import main
from torchfra.cli.run import run

if __name__ == "__main__":
    run(main)
