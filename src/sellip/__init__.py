"""sellip: sparse ellipsometry (Hwang et al., SIGGRAPH 2022) as a reproducible workflow.

The library is organised by stage; every computation is importable and tested:

- :mod:`sellip.conventions` -- camera axes, Stokes frame, polarizer angles (stated once).
- :mod:`sellip.polar` -- Stokes/Mueller algebra.
- :mod:`sellip.fresnel`, :mod:`sellip.microfacet` -- dielectric Fresnel terms, GGX and Smith G.
- :mod:`sellip.pbrdf` -- the three-lobe polarimetric BRDF (full and coaxial forms).
"""

__version__ = "0.1.0"
