"""Test-wide settings: float64 available in JAX (kernels take their dtype from the inputs)."""

import jax

jax.config.update("jax_enable_x64", True)
