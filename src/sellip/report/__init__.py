"""What a person reads: renders, maps, previews, figures of merit (above fit).

Novel-view and new-light renders, Mueller/AoLP/DoP images, parameter maps, HDR previews, and the figures
of merit of docs/design.md §8 (metrics.json).

Modules and what they export (each name is importable from here too)::

    export: Exports of a final model that other tools open (issue #40): glTF 2.0 binary and per-map colour PLYs
        GLTF_ATTRIBUTES, up_rotation
    figures_of_merit: Figures of merit of a reconstructed model (docs/design.md §8): parameters, geometry, re-render
      PSNR, stage timings
        PSNR_MAX_DB, transform_mesh, camera_alignment, truth_reprojection, eta_per_material, parameter_errors,
        geometry_errors, geometry_series, psnr, stage_timings, vertex_errors
    materials: The per-material table of a final model (``final/materials.csv``; issue #40)
        MaterialsError, validate_materials, median_interval, material_table, read_materials, BOOTSTRAP_SEED,
        PATCH_FRACTION, SHARED_STD_FACTOR, patch_labels, block_median_interval, eta_interval, estimating_vertices
    metrics: The figures of merit of a reconstruction (docs/design.md §8; rule ``evaluate_model``): normals, η per
      material and per vertex, albedo, roughness, Chamfer and Hausdorff, held-out and new-light PSNR, the geometry's
      convergence over the iterations -> ``metrics.json`` (:func:`evaluate_model`)
        confident_vertices, view_psnr, evaluate_model, headline_figures, material_support
    outputs: Renders, Mueller-matrix images, AoLP/DoP images and parameter maps of a model (docs/design.md §1 outputs,
      paper Fig. 10)
        MAP_SPECS, novel_camera, mueller_image, polarization_images, parameter_maps, fit_scale, save_figure,
        DEFAULT_VIEWS, EvaluateSettings, OutputsError, default_views, render_outputs
    previews: Preview images of HDR analyzer images for people (``snakemake --report``): pure numpy in, uint8 RGB out
        PREVIEW_KINDS, dolp_aolp, preview_images, write_previews
    viewer: The interactive viewer of a final model: ``results/NAME/viewer/``, a static page that works offline (issue
      #40)
        ViewerError, read_pose_table, load_inputs, payload, write_viewer, serve, find_capture, export_results
        DEFAULT_FLASH

See docs/architecture.md for what this package owns and what it may import.
"""

from sellip._exports import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "export": ("GLTF_ATTRIBUTES", "up_rotation"),
    "figures_of_merit": ("PSNR_MAX_DB", "transform_mesh", "camera_alignment", "truth_reprojection",
           "eta_per_material", "parameter_errors", "geometry_errors", "geometry_series", "psnr", "stage_timings",
           "vertex_errors"),
    "materials": ("MaterialsError", "validate_materials", "median_interval", "material_table", "read_materials",
           "BOOTSTRAP_SEED", "PATCH_FRACTION", "SHARED_STD_FACTOR", "patch_labels", "block_median_interval",
           "eta_interval", "estimating_vertices"),
    "metrics": ("confident_vertices", "view_psnr", "evaluate_model", "headline_figures", "material_support"),
    "outputs": ("MAP_SPECS", "novel_camera", "mueller_image", "polarization_images", "parameter_maps", "fit_scale",
           "save_figure", "DEFAULT_VIEWS", "EvaluateSettings", "OutputsError", "default_views",
           "render_outputs"),
    "previews": ("PREVIEW_KINDS", "dolp_aolp", "preview_images", "write_previews"),
    "viewer": ("ViewerError", "read_pose_table", "load_inputs", "payload", "write_viewer", "serve", "find_capture",
           "export_results", "DEFAULT_FLASH"),
})
