"""`torchfra make-recording` as a script (the same flags): ``python scripts/make_recording.py --help``."""
from torchfra.cli.make_recording import main
from torchfra.cli.run import run

if __name__ == "__main__":
    run(main)
