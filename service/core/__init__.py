"""Service configuration and shared plumbing."""
