"""`torchfra virtual-dic` as a script (the same flags): ``python scripts/virtual_dic.py --help``."""
from torchfra.cli.run import run
from torchfra.cli.virtual_dic import main

if __name__ == "__main__":
    run(main)
