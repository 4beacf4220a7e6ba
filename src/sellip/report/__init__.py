"""What a person reads: renders, maps, previews, figures of merit (above fit).

Novel-view and new-light renders, Mueller/AoLP/DoP images, parameter maps, HDR previews, and the figures
of merit of DESIGN §8 (metrics.json).

Modules and what they export (each name is importable from here too)::

    evaluate: Figures of merit of a reconstructed model (DESIGN §8): parameters, geometry, re-render PSNR, stage
      timings
        PSNR_PEAK_PERCENTILE, PSNR_MAX_DB, FIT_RULE, transform_mesh, camera_alignment, eta_per_material,
        parameter_errors, geometry_errors, geometry_series, psnr, render_mask, stage_timings, vertex_errors
    metrics: The figures of merit of a reconstruction (DESIGN §8; rule ``evaluate_model``): normals, η per material
      and per vertex, albedo, roughness, Chamfer and Hausdorff, held-out and new-light PSNR, the geometry's
      convergence over the iterations -> ``metrics.json`` (:func:`evaluate_model`)
        confident_vertices, sfm_mode, geometry_convergence, view_psnr, evaluate_model, headline_figures
    outputs: Renders, Mueller-matrix images, AoLP/DoP images and parameter maps of a model (DESIGN §1 outputs, paper
      Fig. 10)
        NEW_LIGHT_OFFSET_M, NOVEL_ELEVATION_DEG, MUELLER_BASIS, DARK_FRACTION, MAP_SPECS, object_center,
        novel_camera, moved_flash, mueller_image, polarization_images, parameter_maps, fit_scale, tone_map,
        draw_map, map_figure, grid_figure, mueller_figure, polarization_figure, timings_figure, convergence_figure,
        save_figure, write_renders, DEFAULT_VIEWS, OutputsError, default_views, model_confidence, render_outputs
    previews: Preview images of HDR analyzer images for people (``snakemake --report``): pure numpy in, uint8 RGB
      out
        PREVIEW_KINDS, WHITE_PERCENTILE, srgb_encode, to_uint8, linear_stokes, dolp_aolp, aolp_colors,
        preview_images, write_previews

See docs/architecture.md for what this package owns and what it may import.
"""

from sellip._exports import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "evaluate": ("PSNR_PEAK_PERCENTILE", "PSNR_MAX_DB", "FIT_RULE", "transform_mesh", "camera_alignment",
           "eta_per_material", "parameter_errors", "geometry_errors", "geometry_series", "psnr", "render_mask",
           "stage_timings", "vertex_errors"),
    "metrics": ("confident_vertices", "sfm_mode", "geometry_convergence", "view_psnr", "evaluate_model",
           "headline_figures"),
    "outputs": ("NEW_LIGHT_OFFSET_M", "NOVEL_ELEVATION_DEG", "MUELLER_BASIS", "DARK_FRACTION", "MAP_SPECS",
           "object_center", "novel_camera", "moved_flash", "mueller_image", "polarization_images",
           "parameter_maps", "fit_scale", "tone_map", "draw_map", "map_figure", "grid_figure", "mueller_figure",
           "polarization_figure", "timings_figure", "convergence_figure", "save_figure", "write_renders",
           "DEFAULT_VIEWS", "OutputsError", "default_views", "model_confidence", "render_outputs"),
    "previews": ("PREVIEW_KINDS", "WHITE_PERCENTILE", "srgb_encode", "to_uint8", "linear_stokes", "dolp_aolp",
           "aolp_colors", "preview_images", "write_previews"),
})
