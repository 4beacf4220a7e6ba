"""sellip.report."""
