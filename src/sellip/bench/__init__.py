"""Benchmarks that run whole workflows to measure them (above report).

The speed-accuracy sweep, the stability suite, the accuracy ladder and the scale runs: each plans
Snakemake runs of the workflow, runs them and tabulates what they measured (docs/benchmarks.md).

Modules and what they export (each name is importable from here too)::

    calibration: How careful a calibration must be, on whole reconstructions (issue #39 item 7): the workflow run on one
      synthetic capture of ``sphere_ior`` shot by the synthetic device of ``sellip synth-calibration``, once per
      description of that device: the truth (with two noise seeds, the noise floor), the truth with one error put in
      (flash position, flash polarizer angle, fx, a colour matrix from a noisy chart), and the description ``sellip
      calibrate`` measured on a synthetic calibration set of the same device (docs/calibration.md, "How careful to be")
        FULL_SIZE_ERRORS, PERTURBATIONS, perturb_description, perturbed_capture, noisy_chart_matrix, description_errors,
        sensitivity_markdown, run_sensitivity
    figures: The documented figures (issue #49 item 6): the README's accuracy table, each number read from its table
      row (found by its command) and from the run's metrics.json, compared within a tolerance per kind
      (``sellip figures``; docs/benchmarks.md, "Paper figures by one command")
        FiguresError, Run, Figure, TOLERANCES, RUNS, FIGURES, NOT_COVERED, run_named, table_row, documented, measured,
        Comparison, tolerance_of, compare, select, tolerance_line, document_problems, check, report_lines, provenance,
        record
    intervals: Coverage of the per-material eta intervals of ``final/materials.csv`` (issue #49 item 4), replayed on
      finished runs with a ground truth (``benchmarks/replay_intervals.py``; docs/viewer.md quotes it)
        ROW_COLUMNS, run_renderer, capture_of, material_rows, intervals, fit_shared_factor, coverage,
        CORRELATION_EDGES, residual_correlation
    ladder: The accuracy ladder (docs/accuracy.md): where the error of a reconstruction enters, rung by rung
        render_hdr, fit_true_mesh, figures, eta_by_albedo_mode, albedo_mode_text, resampled_truth,
        psnr_ceiling
    noise_seeds: Whole runs over sensor-noise seeds and core counts (issue #49): the demo over seeds x 1 and 2 cores
      against its targets (``benchmarks/demo_seeds.py``), the suite's scenes' decisions over seeds
      (``benchmarks/suite_seeds.py``; docs/reproducibility.md)
        TARGETS, demo_overrides, seed_run_config, seed_captures, run_name, run_seed, seed_row, with_figures,
        seed_summary, decision_agreement
    renderers: Both renderers side by side (issue #36): the figures of runs on captures of the same scenes rendered by
      sellip and by Mitsuba 3 (stability-suite cases, :mod:`sellip.bench.stability`), with the share of vertices that
      got a single-scattering lobe their ground truth does not have
        single_scattering_shares, false_single_scattering, renderer_markdown
    replay: The command line shared by the replay benchmarks (``benchmarks/replay_*.py``): a run's results folder, one
      of its passes and the capture's ground truth
        replay_parser, ignore_snakemake_zarr_warnings, clustering_overrides_and_truth
    reproducibility: Reproducibility of the material clustering's discrete decisions (issue #49): the clustering of a
      finished run's stored per-vertex fit replayed under perturbations that carry no information (1e-9 noise, vertex
      order, seed, a 90 % subsample) and the distribution of each decision (``benchmarks/reproducibility.py``;
      docs/reproducibility.md)
        KINDS, perturbed_inputs, replay, decisions, summarise, merge_rule
    scale: How each stage's cost grows with the capture (issue #20): per-job costs of measured workflow runs, a cost
      model fitted to them, and the time it predicts for a capture that was not run (docs/speed.md, "Scale")
        CaptureSize, size_terms, job_costs, rule_costs, fit_cost_model, predict
    silhouettes: How well the silhouettes of a run's photographs match the true ones: the ground-truth mesh ray-cast
      through each pixel centre of the capture's true cameras, against
      :func:`sellip.geometry.silhouettes.silhouette_masks` of the run's HDR views under several cuts
      (``benchmarks/silhouette_iou.py``; docs/geometry.md quotes it); how far the photographs' silhouettes lie
      outside the true or a fitted model's, as the geometry update measures it (``benchmarks/silhouette_offsets.py``)
        agreement, silhouette_agreement, cut_difference, model_offsets
    stability: The stability suite (issue #9): small reconstructions built to hit the known failure modes
        BASE_VIEWS, StabilityError, CASES, CASE_NAMES, held_out_views, case_config, perturb_along_normals,
        perturb_mesh_file, miscalibrate_flash, damage_frames, snakemake_command, failure_reason, run_snakemake,
        missing_packages, run_suite
    stability_table: The stability suite's measurements: one row per case from its results folder (figures of merit,
      non-finite outputs, how well confidence flags bad vertices), the table's schema, and the markdown tables of
      docs/benchmarks.md
        Case, rank_auc, confidence_flagging, nonfinite_outputs, COLUMNS, case_row, validate_table
    sweep: Speed-accuracy sweep of the whole workflow (issue #9): one factor at a time from a base configuration
        UPSTREAM_RULES, UPSTREAM_OUTPUTS, link_upstream, SnakemakeRunner, xla_compile_seconds, RECORD, run_sweep
    sweep_plan: What the speed-accuracy sweep varies (:class:`Factor`, the presets), the nested-config helpers (get,
      set, merge, the defaults of config/config.yaml) and the plan of runs (:class:`Variant`, one per factor value and
      scene), with the checkout (``REPO``) whose Snakefile runs them and the sweep's error
        SweepError, Factor, FACTORS, PRESETS, get_key, set_key, merge, Variant, plan_variants, variant_overrides
        declared_default
    sweep_report: The sweep's report (``sellip bench-sweep``): η per material of a run's results against the truth, the
      vertices per model, and the markdown tables and files the sweep writes (:func:`write_outputs`)
        tables_markdown, write_outputs, write_csv
    sweep_tables: The sweep's results: Pareto front, the table (one row per run, pandera-checked), the speed- accuracy
      chart, the paper's comparisons (Table 1 eta, augmentation, sigma_ss, model selection) and markdown tables
        pareto_front, SWEEP_COLUMNS, job_cpu_seconds, sweep_row, sweep_table, sweep_figure, front_marks, PAPER_TABLE1,
        ior_table, augmentation_table, sigma_ss_table, model_selection_table, markdown_table

See docs/architecture.md for what this package owns and what it may import.
"""

from sellip._exports import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "calibration": ("FULL_SIZE_ERRORS", "PERTURBATIONS", "perturb_description", "perturbed_capture",
           "noisy_chart_matrix", "description_errors", "sensitivity_markdown", "run_sensitivity"),
    "figures": ("FiguresError", "Run", "Figure", "TOLERANCES", "RUNS", "FIGURES", "NOT_COVERED", "run_named",
           "table_row", "documented", "measured", "Comparison", "tolerance_of", "compare", "select", "tolerance_line",
           "document_problems", "check", "report_lines", "provenance", "record"),
    "intervals": ("ROW_COLUMNS", "run_renderer", "capture_of", "material_rows", "intervals", "fit_shared_factor",
           "coverage", "CORRELATION_EDGES", "residual_correlation"),
    "ladder": ("WORKFLOW_RUNGS", "capture_tag", "workflow_run_name", "render_hdr", "fit_true_mesh", "figures",
           "eta_by_albedo_mode", "albedo_mode_text", "resampled_truth", "psnr_ceiling"),
    "noise_seeds": ("TARGETS", "demo_overrides", "seed_run_config", "seed_captures", "run_name", "run_seed",
           "seed_row", "with_figures", "seed_summary", "decision_agreement"),
    "renderers": ("single_scattering_shares", "false_single_scattering", "renderer_markdown"),
    "replay": ("replay_parser", "ignore_snakemake_zarr_warnings", "clustering_overrides_and_truth"),
    "reproducibility": ("KINDS", "perturbed_inputs", "replay", "decisions", "summarise", "merge_rule"),
    "scale": ("CaptureSize", "size_terms", "job_costs", "rule_costs", "fit_cost_model", "predict"),
    "silhouettes": ("agreement", "silhouette_agreement", "cut_difference", "model_offsets"),
    "stability": ("BASE_VIEWS", "StabilityError", "CASES", "CASE_NAMES", "held_out_views", "case_config",
           "perturb_along_normals", "perturb_mesh_file", "miscalibrate_flash", "damage_frames", "snakemake_command",
           "failure_reason", "run_snakemake", "run_failure", "write_row", "missing_packages", "run_suite"),
    "stability_table": ("Case", "rank_auc", "confidence_flagging", "nonfinite_outputs", "COLUMNS", "case_row",
           "validate_table", "geometry_folds", "cluster_decisions", "stability_markdown"),
    "sweep": ("UPSTREAM_RULES", "UPSTREAM_OUTPUTS", "link_upstream", "SnakemakeRunner", "xla_compile_seconds",
           "RECORD", "run_sweep"),
    "sweep_plan": ("SweepError", "Factor", "FACTORS", "PRESETS", "get_key", "set_key", "merge", "Variant",
           "plan_variants", "variant_overrides", "declared_default"),
    "sweep_report": ("tables_markdown", "write_outputs", "write_csv"),
    "sweep_tables": ("pareto_front", "SWEEP_COLUMNS", "job_cpu_seconds", "sweep_row", "sweep_table", "sweep_figure",
           "front_marks", "PAPER_TABLE1", "ior_table", "augmentation_table", "sigma_ss_table",
           "model_selection_table", "markdown_table"),
})
