"""sellip.capture."""
