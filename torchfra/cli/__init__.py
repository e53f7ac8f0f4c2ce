"""The ``torchfra`` command and its subcommands (``torchfra --help``).

Each subcommand is a module here with ``main(argv)``: parse the flags, call the library, write
``runs/<name>/``. ``scripts/<name>.py`` is a thin wrapper of the same ``main`` (same flags), for those
who run training-style scripts. :mod:`.run` is how every command ends: a user's mistake is one
paragraph on stderr with exit status 2, never a traceback.
"""
