"""The per-vertex fit and everything an iteration does with it (above capture and geometry).

Observations of a mesh, the batched Levenberg-Marquardt fit with variable projection, its records and
parameterization, shards and their gather, material clusters and per-cluster lobes (augmentation), model
selection, the geometry update job, and the final model.

Modules and what they export (each name is importable from here too)::

    augment_pass: One augmentation pass (rule ``cluster_lobes``; paper §4.3, docs/design.md §7): the material clusters,
      each cluster's model chosen on held-out vertices, each cluster's lobe fitted, written to the cluster-lobes
      directory (:func:`cluster_and_fit_lobes`)
        cluster_rows, cluster_and_fit_lobes
    cluster_support: How often the material clustering comes out again (docs/reproducibility.md, "Saying when it is
      fragile"): the clustering repeated on seeded subsamples of the clustered vertices, each cluster matched to the
      repeats' clusters, and the materials the repeats split off
        SUPPORT_KEEP, RECOVERED_JACCARD, cluster_support, split_from, clustering_support
    clusters: Material clusters (paper §4.3, docs/design.md §7; docs/augment.md): K-means on the feature (eta, rho_d
      RGB) of the confidently fitted vertices, K chosen by BIC; small clusters merged; spatially incoherent clusters (a
      cut through one material's noise) merged; regions of another albedo inside a cluster added; a material cut along
      its eta merged
        ETA_SCALE, VARIANCE_FLOOR, AugmentSettings, Clustering, cluster_features, spatial_coherence, nearest_vertices,
        vertex_coherence, robust_mahalanobis, albedo_separation, one_mode, same_eta_by_albedo, find_eta_cut,
        cluster_materials, squared_distances
    convergence: Convergence of the outer loop (docs/speed.md "Convergence"): the geometry update's verdict, and the
      jobs of later iterations that pass their inputs through (the DAG kept static)
        PASSED_THROUGH, ConvergenceSettings, judge, converged_at, pass_through, loop_convergence
    evidence: No result without evidence (docs/design.md §9): a pass whose fit covers too little of the visible
      surface stops the run with what is missing (views, coverage, exposure)
        MIN_FITTED_SHARE, EvidenceError, fitted_share, check_evidence
    finalize: The final model (rule ``finalize_model``; docs/design.md §4): per-material η and lobes with per-vertex
      deviations where a vertex's data demand them, unfitted vertices interpolated from their neighbours, confidence,
      ``model``: ``final/model.ply`` and ``final/params.zarr`` (:func:`finalize_model`)
        FinalSettings, finalize_model, vertex_cluster_support
    geometry_jobs: The updates between iterations
        GeometryUpdateSettings, raw_camera, predicted_diffuse, measure_silhouettes, iteration_model, refine_geometry,
        refine_poses
    kernels: Compiled kernels that later processes load instead of tracing again (docs/speed.md)
        code_version, enable, kernel
    lobe_store: The cluster-lobes output directory (``labels.npy``, ``models.npy``, ``lobes.csv``, ``lobes.png``,
      ``clusters.json``): its schema, readers, the settings it records, and the lobe plot (paper Fig. 7b)
        LOBE_COLUMNS, read_lobes, read_labels, previous_labels, pass_clusters, read_models, recorded_fit_settings,
        clustering_settings, load_rows
    lobes: Per-cluster specular lobes and virtual samples (paper §4.3 "Specular and single scattering loss", Eqs.
      24-25): a cluster's eta, sigma_s, sigma_ss, rho_s, rho_ss fitted to the pooled observations of its vertices with a
      per-sample half-angle error Delta theta_h and the regularizer lambda_theta Delta theta_h^2; per vertex, M virtual
      specular samples rendered from its cluster's lobe; per-material values with per-vertex deviations where a vertex's
      data demand them
        ClusterLobe, fit_cluster_lobe, virtual_samples, cluster_medians, material_or_own
    observe: Per-vertex, per-view observations for the pBRDF fit (docs/design.md §2 observe, §5)
        MISSING_POSES, ObserveError, ObserveSettings, ObserveMesh, read_mesh, bilinear_sample, silhouette_distance,
        relative_slope, Observer, ObservationWriter, open_observations, load_observations
    observe_mesh: Observe a mesh in every view (docs/design.md §2 observe; rule ``gather_observations``): pair the HDR
      views with the cameras, check the scale, and write the observation store (:func:`observe_mesh`)
        pair_views, spread_subset, observe_mesh
    parameterization: The fit's bounded parameterization (scaled sigmoids: eta in ETA_BOUNDS, sigma_s <= sigma_ss -
      LOBE_GAP) and the geometry and reflectance of the virtual specular samples (paper Eq. 24)
        eta_at_bound, decode_parameters, encode_parameters, virtual_reflectance
    records: The per-vertex fit's settings and records: :class:`FitSettings`, the status codes, the model codes (which
      lobes), :class:`Observations` (the fit's input), :class:`VirtualSamples`, :class:`FitResult`
        STATUS_FITTED, STATUS_TOO_FEW_VIEWS, ETA_BOUNDS, MODELS, FitSettings, model_of, Observations, VirtualSamples,
        FitResult, STATUS_FAILED, DTYPES, FitJobSettings
    residuals: The residuals of one vertex (docs/design.md §5): the linear parameters (rho_d RGB, rho_s, rho_ss RGB)
      solved in closed form with non-negativity inside the residual (variable projection), then
        solve_spd, nnls_specular, model_terms, linear_solution, measured_dop, vertex_residuals
    selection: Model selection (docs/design.md §7): which lobes a material cluster needs, and fitting vertices by model
        SelectionSettings, settings_for_model, allowed_models, cap_models, split_vertices, fold_splits, choose,
        decision_margin, margin_confidence, cluster_margins, in_family, nested_fits, select_model, fit_by_model
    shard: One fit shard (rule ``fit_pbrdf``) and the gather of an iteration's shards into ``fit.zarr`` (rule
      ``gather_fit``): the fit settings from ``--set KEY=VALUE`` pairs, XLA's persistent compilation cache,
      :func:`fit_shard` and :func:`gather_shards`; what the job may use (:func:`memory_budget`) and the message that
      names the shard count that fits
        parse_shard, settings_from_pairs, overrides_from_pairs, available_memory, memory_budget, fit_shard, fit_rows,
        gather_shards
    shard_plan: How the fit's vertices are split into shards, without JAX: each shard's rows, the memory one shard's
      job needs (:data:`SHARD_MEMORY`), and the count the workflow plans before it runs (config ``fit.shards``
      raised to what ``fit.mem_mb`` holds)
        shard_rows, largest_shard, ShardMemory, SHARD_MEMORY, ShardMemoryError, planned_shards, fit_shard_plan
    simulate: Per-vertex observations simulated with the full forward model: inputs with known answers for the fit's
      tests and benchmark (no mesh, no images: one surface point per vertex)
        vertex_observations
    solver: The batched Levenberg-Marquardt of the per-vertex fit (JAX): damping, steps, rounds, the roughness starts,
      the diffuse eta hold's constants; each vertex an independent small problem (paper §4.3, docs/design.md §5, §7)
      over 5 nonlinear unknowns (normal offset (2), eta, sigma_s, sigma_ss)
        free_parameters, lm_rounds, ROUGHNESS_GRID, pick_best_start
    vertex_fit: The per-vertex polarimetric fit (:func:`fit_vertices`): view selection, batching by view count, the
      solver, the robust pass, the diffuse eta hold, finalize (status, confidence, std), and the default prior
        robust_weights, select_and_prepare, fit_vertices, default_prior

See docs/architecture.md for what this package owns and what it may import.
"""

from sellip._exports import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "augment_pass": ("cluster_rows", "cluster_and_fit_lobes"),
    "clusters": ("ETA_SCALE", "VARIANCE_FLOOR", "AugmentSettings", "Clustering", "cluster_features",
           "spatial_coherence", "nearest_vertices", "vertex_coherence", "robust_mahalanobis", "albedo_separation",
           "one_mode", "same_eta_by_albedo", "find_eta_cut", "cluster_materials", "squared_distances"),
    "cluster_support": ("SUPPORT_KEEP", "RECOVERED_JACCARD", "cluster_support", "split_from", "clustering_support"),
    "convergence": ("PASSED_THROUGH", "ConvergenceSettings", "judge", "converged_at", "pass_through",
           "loop_convergence"),
    "evidence": ("MIN_FITTED_SHARE", "EvidenceError", "fitted_share", "check_evidence"),
    "finalize": ("FinalSettings", "finalize_model", "vertex_cluster_support"),
    "geometry_jobs": ("GeometryUpdateSettings", "raw_camera", "predicted_diffuse", "measure_silhouettes",
                      "iteration_model", "refine_geometry", "refine_poses"),
    "kernels": ("code_version", "enable", "kernel"),
    "lobe_store": ("LOBE_COLUMNS", "read_lobes", "read_labels", "previous_labels", "pass_clusters", "read_models",
           "recorded_fit_settings", "clustering_settings", "load_rows"),
    "lobes": ("ClusterLobe", "fit_cluster_lobe", "virtual_samples", "cluster_medians", "material_or_own"),
    "observe": ("MISSING_POSES", "ObserveError", "ObserveSettings", "ObserveMesh", "read_mesh", "bilinear_sample",
           "silhouette_distance", "relative_slope", "Observer", "ObservationWriter", "open_observations",
           "load_observations"),
    "observe_mesh": ("pair_views", "spread_subset", "observe_mesh"),
    "parameterization": ("eta_at_bound", "decode_parameters", "encode_parameters", "virtual_reflectance"),
    "records": ("STATUS_FITTED", "STATUS_TOO_FEW_VIEWS", "ETA_BOUNDS", "MODELS", "FitSettings", "model_of",
           "Observations", "VirtualSamples", "FitResult", "STATUS_FAILED", "DTYPES", "FitJobSettings"),
    "residuals": ("solve_spd", "nnls_specular", "model_terms", "linear_solution", "measured_dop",
           "vertex_residuals"),
    "selection": ("SelectionSettings", "settings_for_model", "allowed_models", "cap_models", "split_vertices",
           "fold_splits", "choose", "decision_margin", "margin_confidence", "cluster_margins", "in_family",
           "nested_fits", "select_model", "fit_by_model"),
    "shard": ("parse_shard", "settings_from_pairs", "overrides_from_pairs", "available_memory", "memory_budget",
           "fit_shard", "fit_rows", "gather_shards"),
    "shard_plan": ("shard_rows", "largest_shard", "ShardMemory", "SHARD_MEMORY", "ShardMemoryError",
           "planned_shards", "fit_shard_plan"),
    "simulate": ("vertex_observations",),
    "solver": ("free_parameters", "lm_rounds", "ROUGHNESS_GRID", "pick_best_start"),
    "vertex_fit": ("robust_weights", "select_and_prepare", "fit_vertices", "default_prior"),
})
