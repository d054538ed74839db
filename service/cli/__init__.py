"""The ``mcam`` command line: one module per command, registered in :mod:`service.cli.main`."""
