"""Reconstruction workers: consume frames and jobs from the queue, write results."""
