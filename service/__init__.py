"""The user-facing layer: REST API, web viewer and the ``mcam`` command line."""
