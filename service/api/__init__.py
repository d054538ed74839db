"""The REST API: dependencies, errors, uploads, previews and the resource routers."""
