"""sellip: sparse ellipsometry (Hwang et al., SIGGRAPH 2022) as a reproducible workflow.

The library is organised by stage; every computation is importable and tested:

- :mod:`sellip.model.conventions` -- camera axes, Stokes frame, polarizer angles (stated once).
- :mod:`sellip.model.polar` -- Stokes/Mueller algebra.
- :mod:`sellip.model.fresnel`, :mod:`sellip.model.microfacet` -- dielectric Fresnel terms, GGX and Smith G.
- :mod:`sellip.model.pbrdf` -- the three-lobe polarimetric BRDF (full and coaxial forms).
"""

__version__ = "0.1.0"
