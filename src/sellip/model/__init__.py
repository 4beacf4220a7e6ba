"""sellip.model."""
