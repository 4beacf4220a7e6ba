"""sellip.geometry."""
