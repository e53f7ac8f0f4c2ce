"""``python -m torchfra`` is the ``torchfra`` command."""
from torchfra.cli.main import main

main()
