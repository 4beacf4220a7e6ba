"""What a person reads: renders, maps, previews, figures of merit (above fit).

Novel-view and new-light renders, Mueller/AoLP/DoP images, parameter maps, HDR previews, and the figures
of merit of docs/design.md §8 (metrics.json).

Modules and what they export (each name is importable from here too)::

    evaluate: Figures of merit of a reconstructed model (docs/design.md §8): parameters, geometry, re-render PSNR, stage
      timings
        PSNR_PEAK_PERCENTILE, PSNR_MAX_DB, FIT_RULE, transform_mesh, camera_alignment, eta_per_material,
        parameter_errors, geometry_errors, nearest_normal_errors, geometry_series, psnr, render_mask, stage_timings,
        vertex_errors
    export: Exports of a final model that other tools open (issue #40): glTF 2.0 binary and per-map colour PLYs
        GLTF_ATTRIBUTES, MAP_RANGE_PERCENTILES, CATEGORY_COLORS, MapData, MAP_LABELS, MAP_NAMES, model_maps,
        viridis, map_colors, write_map_plys, up_rotation, base_color, write_glb
    materials: The per-material table of a final model (``final/materials.csv``; issue #40)
        BOOTSTRAP_ROUNDS, BOOTSTRAP_SEED, MAD_TO_SD, COLUMNS, GT_COLUMNS, MaterialsError, materials_schema,
        validate_materials, vertex_areas, median_interval, material_table, write_materials, read_materials
    metrics: The figures of merit of a reconstruction (docs/design.md §8; rule ``evaluate_model``): normals, η per material
      and per vertex, albedo, roughness, Chamfer and Hausdorff, held-out and new-light PSNR, the geometry's
      convergence over the iterations -> ``metrics.json`` (:func:`evaluate_model`)
        confident_vertices, sfm_mode, geometry_convergence, view_psnr, evaluate_model, headline_figures
    outputs: Renders, Mueller-matrix images, AoLP/DoP images and parameter maps of a model (docs/design.md §1 outputs, paper
      Fig. 10)
        NEW_LIGHT_OFFSET_M, NOVEL_ELEVATION_DEG, MUELLER_BASIS, DARK_FRACTION, MAP_SPECS, object_center,
        novel_camera, moved_flash, mueller_image, polarization_images, parameter_maps, fit_scale, tone_map,
        draw_map, map_figure, grid_figure, mueller_figure, polarization_figure, timings_figure, convergence_figure,
        save_figure, write_renders, DEFAULT_VIEWS, OutputsError, default_views, model_confidence, render_outputs
    previews: Preview images of HDR analyzer images for people (``snakemake --report``): pure numpy in, uint8 RGB
      out
        PREVIEW_KINDS, WHITE_PERCENTILE, srgb_encode, to_uint8, linear_stokes, dolp_aolp, aolp_colors,
        preview_images, write_previews
    viewer: The interactive viewer of a final model: ``results/NAME/viewer/``, a static page that works offline
      (issue #40)
        ASSETS, SHADERS, DEFAULT_FLASH, DARK_LEVEL, DEFAULT_SIZE, ViewerError, ViewerInputs, read_light,
        read_pose_table, load_inputs, default_exposure, payload, shader_sources, write_viewer, serve, maps_of,
        find_capture, ground_truth_for, export_results

See docs/architecture.md for what this package owns and what it may import.
"""

from sellip._exports import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "evaluate": ("PSNR_PEAK_PERCENTILE", "PSNR_MAX_DB", "FIT_RULE", "transform_mesh", "camera_alignment",
           "eta_per_material", "parameter_errors", "geometry_errors", "nearest_normal_errors", "geometry_series",
           "psnr", "render_mask", "stage_timings", "vertex_errors"),
    "export": ("GLTF_ATTRIBUTES", "MAP_RANGE_PERCENTILES", "CATEGORY_COLORS", "MapData", "MAP_LABELS", "MAP_NAMES",
           "model_maps", "viridis", "map_colors", "write_map_plys", "up_rotation", "base_color", "write_glb"),
    "materials": ("BOOTSTRAP_ROUNDS", "BOOTSTRAP_SEED", "MAD_TO_SD", "COLUMNS", "GT_COLUMNS", "MaterialsError",
           "materials_schema", "validate_materials", "vertex_areas", "median_interval", "material_table",
           "write_materials", "read_materials"),
    "metrics": ("confident_vertices", "sfm_mode", "geometry_convergence", "view_psnr", "evaluate_model",
           "headline_figures"),
    "outputs": ("NEW_LIGHT_OFFSET_M", "NOVEL_ELEVATION_DEG", "MUELLER_BASIS", "DARK_FRACTION", "MAP_SPECS",
           "object_center", "novel_camera", "moved_flash", "mueller_image", "polarization_images",
           "parameter_maps", "fit_scale", "tone_map", "draw_map", "map_figure", "grid_figure", "mueller_figure",
           "polarization_figure", "timings_figure", "convergence_figure", "save_figure", "write_renders",
           "DEFAULT_VIEWS", "OutputsError", "default_views", "model_confidence", "render_outputs"),
    "previews": ("PREVIEW_KINDS", "WHITE_PERCENTILE", "srgb_encode", "to_uint8", "linear_stokes", "dolp_aolp",
           "aolp_colors", "preview_images", "write_previews"),
    "viewer": ("ASSETS", "SHADERS", "DEFAULT_FLASH", "DARK_LEVEL", "DEFAULT_SIZE", "ViewerError", "ViewerInputs",
           "read_light", "read_pose_table", "load_inputs", "default_exposure", "payload", "shader_sources",
           "write_viewer", "serve", "maps_of", "find_capture", "ground_truth_for", "export_results"),
})
