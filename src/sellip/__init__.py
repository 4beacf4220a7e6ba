"""sellip: sparse ellipsometry (Hwang et al., SIGGRAPH 2022) as a reproducible workflow.

The library is split by stage family; each subpackage's ``__init__`` lists its modules and public API, and
``docs/architecture.md`` draws the packages, the data between the stages and what each may import:

- :mod:`sellip.model` -- conventions, Stokes/Mueller, Fresnel, GGX, the pBRDF, parameter stores, the renderer.
- :mod:`sellip.capture` -- the capture format, the sensor, ingest (linearize, HDR merge), synthetic captures.
- :mod:`sellip.geometry` -- cameras and poses (SfM), silhouettes, the hull and initial mesh, the geometry update.
- :mod:`sellip.fit` -- observations, the per-vertex fit, shards, clusters and lobes, model selection, the final model.
- :mod:`sellip.report` -- renders, Mueller/AoLP/DoP images, maps, previews, figures of merit.
- :mod:`sellip.bench` -- the sweep, the stability suite, the accuracy ladder, the scale runs.
- :mod:`sellip.stages` -- one thin adapter per ``sellip`` command (:mod:`sellip.cli`); :mod:`sellip.jobs` and
  :mod:`sellip.timing` are what every stage uses to write its outputs and time itself.
"""

__version__ = "0.1.0"
