"""sellip.bench."""
