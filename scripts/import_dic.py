"""`torchfra import-dic` as a script (the same flags): ``python scripts/import_dic.py --help``."""
from torchfra.cli.import_dic import main
from torchfra.cli.run import run

if __name__ == "__main__":
    run(main)
