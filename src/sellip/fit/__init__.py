"""sellip.fit."""
