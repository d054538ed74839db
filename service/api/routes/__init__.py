"""REST API resources, one router module per resource (listed in service.main.ROUTERS)."""
