"""The per-vertex fit and everything an iteration does with it (above capture and geometry).

Observations of a mesh, the batched Levenberg-Marquardt fit with variable projection, its records and
parameterization, shards and their gather, material clusters and per-cluster lobes (augmentation), model
selection, the geometry update job, and the final model.

Modules and what they export (each name is importable from here too)::

    augment_pass: One augmentation pass (rule ``cluster_lobes``; paper §4.3, DESIGN §7): the material clusters, each
      cluster's model chosen on held-out vertices, each cluster's lobe fitted, written to the cluster-lobes directory
      (:func:`cluster_and_fit_lobes`)
        cluster_rows, cluster_and_fit_lobes
    clusters: Material clusters (paper §4.3, DESIGN §7; docs/augment.md): K-means on the feature (eta, rho_d RGB) of
      the confidently fitted vertices, K chosen by BIC; small clusters merged; spatially incoherent clusters (a cut
      through one material's noise) merged; regions of another albedo inside a cluster added; a material cut along its
      eta merged
        CHROMA_SCALE, LOG_BRIGHTNESS_SCALE, ETA_SCALE, VARIANCE_FLOOR, REGION_OUTLIER_P, REGION_EPS,
        REGION_MIN_SAMPLES, REGION_FIT_POINTS, CUT_ALBEDO_SD, CUT_MODE_POINTS, CUT_ETA_SE, CUT_MODES_ALBEDO_SD,
        AugmentSettings, Clustering, cluster_features, kmeans, bic, choose_k, spatial_coherence, nearest_vertices,
        vertex_coherence, DEGENERATE_VARIANCE, cluster_materials
    finalize: The final model (rule ``finalize_model``; DESIGN §4): per-material η and lobes with per-vertex
      deviations where a vertex's data demand them, unfitted vertices interpolated from their neighbours, confidence,
      ``model``: ``final/model.ply`` and ``final/params.zarr`` (:func:`finalize_model`)
        finalize_model
    kernels: Compiled kernels that later processes load instead of tracing again (docs/speed.md)
        code_version, enable, Kernel, kernel
    lobe_store: The cluster-lobes output directory (``labels.npy``, ``models.npy``, ``lobes.csv``, ``lobes.png``,
      ``clusters.json``): its schema, readers, the settings it records, and the lobe plot (paper Fig. 7b)
        LOBE_COLUMNS, lobes_schema, read_lobes, read_models, recorded_fit_settings, clustering_settings, load_rows,
        plot_lobes
    lobes: Per-cluster specular lobes and virtual samples (paper §4.3 "Specular and single scattering loss", Eqs.
      24-25): a cluster's eta, sigma_s, sigma_ss, rho_s, rho_ss fitted to the pooled observations of its vertices with
      a per-sample half-angle error Delta theta_h and the regularizer lambda_theta Delta theta_h^2; per vertex, M
      virtual specular samples rendered from its cluster's lobe; per-material values with per-vertex deviations where
      a vertex's data demand them
        ClusterLobe, lobe_fit_settings, fit_cluster_lobe, no_lobe, lobe_sample_losses, lobe_curve, virtual_theta_h,
        virtual_samples, VALUE_SOURCES, cluster_medians, material_or_own
    observe: Per-vertex, per-view observations for the pBRDF fit (DESIGN §2 observe, §5)
        PER_VIEW_ARRAYS, VIEW_AXES, BYTES_PER_OBSERVATION, ObserveError, ObserveSettings, ObserveMesh, read_mesh,
        median_edge_length, raycasting_scene, segments_clear, project_points, inside_image, Footprint,
        bilinear_footprint, bilinear_sample, silhouette_distance, relative_slope, Visibility, ViewObservations,
        Observer, ObservationWriter, VertexObservations, open_observations, load_observations
    observe_mesh: Observe a mesh in every view (DESIGN §2 observe; rule ``gather_observations``): pair the HDR views
      with the cameras, check the scale, and write the observation store (:func:`observe_mesh`)
        MISSING_POSES, UNITS, pair_views, spread_subset, observe_mesh
    parameterization: The fit's bounded parameterization (scaled sigmoids: eta in ETA_BOUNDS, sigma_s <= sigma_ss -
      LOBE_GAP) and the geometry and reflectance of the virtual specular samples (paper Eq. 24)
        tangent_basis, ETA_BOUND_MARGIN, eta_at_bound, virtual_geometry, virtual_reflectance
    records: The per-vertex fit's settings and records: :class:`FitSettings`, the status codes, the model codes
      (which lobes), :class:`Observations` (the fit's input), :class:`VirtualSamples`, :class:`FitResult`
        STATUS_FITTED, STATUS_TOO_FEW_VIEWS, STATUS_FAILED, STATUS_NAMES, ETA_BOUNDS, SIGMA_BOUNDS, LOBE_GAP,
        LOBE_SETS, MODELS, DEFAULT_FIXED_SIGMA_SS, FitSettings, model_of, model_arrays, Observations,
        VirtualSamples, FitResult
    refine: The geometry update of one iteration (rule ``refine_geometry``; docs/geometry_update.md): the fitted
      normals blended by confidence, the photographs' silhouettes measured against the model's predicted photograph,
      and the mesh moved by normal integration (:func:`refine_geometry`)
        raw_camera, predicted_diffuse, measure_silhouettes, refine_geometry
    residuals: The residuals of one vertex (DESIGN §5): the linear parameters (rho_d RGB, rho_s, rho_ss RGB) solved
      in closed form with non-negativity inside the residual (variable projection), then
        solve_spd, measured_dop, DIFFERENCE_STEPS, per_view_error
    selection: Model selection (DESIGN §7): which lobes a material cluster needs, and fitting vertices by model
        SelectionSettings, settings_for_model, allowed_models, cap_models, Selection, split_vertices, choose,
        decision_margin, MARGIN_FULL_CONFIDENCE, margin_confidence, cluster_margins, select_model, fit_by_model
    shard: One fit shard (rule ``fit_pbrdf``) and the gather of an iteration's shards into ``fit.zarr`` (rule
      ``gather_fit``): the shard's vertex rows, the fit settings from ``--set KEY=VALUE`` pairs, XLA's persistent
      compilation cache, :func:`fit_shard` and :func:`gather_shards`; the memory a shard needs (:data:`SHARD_MEMORY`),
      what the job may use (:func:`memory_budget`) and the error that names the shard count that fits
      (:class:`ShardMemoryError`)
        parse_shard, shard_rows, settings_from_pairs, overrides_from_pairs, enable_compilation_cache, largest_shard,
        ShardMemory, SHARD_MEMORY, ShardMemoryError, available_memory, memory_budget, shard_memory_message,
        fit_shard, gather_shards
    simulate: Per-vertex observations simulated with the full forward model: inputs with known answers for the fit's
      tests and benchmark (no mesh, no images: one surface point per vertex)
        vertex_observations
    solver: The batched Levenberg-Marquardt of the per-vertex fit (JAX): damping, steps, rounds, the roughness
      starts, the diffuse eta hold's constants; each vertex an independent small problem (paper §4.3, DESIGN §5, §7)
      over 5 nonlinear unknowns (normal offset (2), eta, sigma_s, sigma_ss)
        Z_LIMIT, PROGRESS_ITERATIONS, STUCK_DAMPING, HOLD_ROUNDS, HOLD_ETA_TOLERANCE, ROUGHNESS_GRID
    vertex_fit: The per-vertex polarimetric fit (:func:`fit_vertices`): view selection, batching by view count, the
      solver, the robust pass, the diffuse eta hold, finalize (status, confidence, std), and the default prior
        select_views, confidence_from_uncertainty, fit_vertices, default_prior

See docs/architecture.md for what this package owns and what it may import.
"""

from sellip._exports import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "augment_pass": ("cluster_rows", "cluster_and_fit_lobes"),
    "clusters": ("CHROMA_SCALE", "LOG_BRIGHTNESS_SCALE", "ETA_SCALE", "VARIANCE_FLOOR", "REGION_OUTLIER_P",
           "REGION_EPS", "REGION_MIN_SAMPLES", "REGION_FIT_POINTS", "CUT_ALBEDO_SD", "CUT_MODE_POINTS", "CUT_ETA_SE",
           "CUT_MODES_ALBEDO_SD", "AugmentSettings", "Clustering", "cluster_features", "kmeans", "bic", "choose_k",
           "spatial_coherence", "nearest_vertices", "vertex_coherence", "DEGENERATE_VARIANCE", "cluster_materials"),
    "finalize": ("finalize_model",),
    "kernels": ("code_version", "enable", "Kernel", "kernel"),
    "lobe_store": ("LOBE_COLUMNS", "lobes_schema", "read_lobes", "read_models", "recorded_fit_settings",
           "clustering_settings", "load_rows", "plot_lobes"),
    "lobes": ("ClusterLobe", "lobe_fit_settings", "fit_cluster_lobe", "no_lobe", "lobe_sample_losses", "lobe_curve",
           "virtual_theta_h", "virtual_samples", "VALUE_SOURCES", "cluster_medians", "material_or_own"),
    "observe": ("PER_VIEW_ARRAYS", "VIEW_AXES", "BYTES_PER_OBSERVATION", "ObserveError", "ObserveSettings",
           "ObserveMesh", "read_mesh", "median_edge_length", "raycasting_scene", "segments_clear",
           "project_points", "inside_image", "Footprint", "bilinear_footprint", "bilinear_sample",
           "silhouette_distance", "relative_slope", "Visibility", "ViewObservations", "Observer",
           "ObservationWriter", "VertexObservations", "open_observations", "load_observations"),
    "observe_mesh": ("MISSING_POSES", "UNITS", "pair_views", "spread_subset", "observe_mesh"),
    "parameterization": ("tangent_basis", "ETA_BOUND_MARGIN", "eta_at_bound", "virtual_geometry",
                         "virtual_reflectance"),
    "records": ("STATUS_FITTED", "STATUS_TOO_FEW_VIEWS", "STATUS_FAILED", "STATUS_NAMES", "ETA_BOUNDS", "SIGMA_BOUNDS",
           "LOBE_GAP", "LOBE_SETS", "MODELS", "DEFAULT_FIXED_SIGMA_SS", "FitSettings", "model_of", "model_arrays",
           "Observations", "VirtualSamples", "FitResult"),
    "refine": ("raw_camera", "predicted_diffuse", "measure_silhouettes", "refine_geometry"),
    "residuals": ("solve_spd", "measured_dop", "DIFFERENCE_STEPS", "per_view_error"),
    "selection": ("SelectionSettings", "settings_for_model", "allowed_models", "cap_models", "Selection",
           "split_vertices", "choose", "decision_margin", "MARGIN_FULL_CONFIDENCE", "margin_confidence",
           "cluster_margins", "select_model", "fit_by_model"),
    "shard": ("parse_shard", "shard_rows", "settings_from_pairs", "overrides_from_pairs", "enable_compilation_cache",
           "largest_shard", "ShardMemory", "SHARD_MEMORY", "ShardMemoryError", "available_memory", "memory_budget",
           "shard_memory_message", "fit_shard", "gather_shards"),
    "simulate": ("vertex_observations",),
    "solver": ("Z_LIMIT", "PROGRESS_ITERATIONS", "STUCK_DAMPING", "HOLD_ROUNDS", "HOLD_ETA_TOLERANCE",
               "ROUGHNESS_GRID"),
    "vertex_fit": ("select_views", "confidence_from_uncertainty", "fit_vertices", "default_prior"),
})
