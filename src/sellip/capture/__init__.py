"""A capture: its format, its sensor and its ingest (above model).

The capture folder (DESIGN §3: capture.yaml, frames.csv, poses.csv, raw frames) read, validated and
written; the polarization mosaic and the sensor simulator; linearize, demosaic and the HDR merge into hdr.zarr;
synthetic scenes and synthetic captures with known truth.

Modules and what they export (each name is importable from here too)::

    assemble: A capture folder (DESIGN §3) from a folder of raw frames and a calibrated device.yaml (``sellip
      capture new``)
        RAW_SUFFIXES, FIELDS, AssembleError, parse_pattern, flash_level, frames_from_pattern, frames_from_csv,
        assemble_capture
    capture_yaml: capture.yaml (DESIGN §3): its JSON schema and :func:`validate_config`, which names the key, what
      was expected and what was found
        CONFIG_SCHEMA, MAX_FIELD_DEG, validate_config
    checks: Unit checks of a capture's numbers against each other (issue #38): lengths that are off by a factor of
      1000 must not pass silently
        DISTANCE_TOLERANCE, UNIT_MATCH, PoseUnitsError, camera_distances, likely_unit, check_pose_units
    files: The capture folder's file names and columns (DESIGN §3), and the errors every reader raises
      (:class:`CaptureError` and its kinds: each names the file, and where it applies the row, column or key)
        CAPTURE_YAML, FRAMES_CSV, POSES_CSV, RAW_DIR, GROUND_TRUTH_DIR, RAWPY_SUFFIXES, TIFF_SUFFIXES, PNG_SUFFIXES,
        FRAME_COLUMNS, POSE_COLUMNS, CaptureError, MissingFileError, ConfigError, UnknownLayoutError, FramesError,
        DuplicateFrameError, FlashLevelError, PosesError, ViewWithoutFramesError, RawFrameError, GROUND_TRUTH_MESH,
        MAX_LISTED_PROBLEMS, more_problems
    hdr: The HDR store ``hdr.zarr`` (DESIGN §2 hdr_merge): one HDR image per view and analyzer (I0, I45, I90, I135,
      RGB, float32, relative radiance) and its valid mask, merged from a view's flash levels (:func:`merge_capture`),
      and its reader (:func:`read_hdr` -> :class:`HDRImages`)
        UNITS, HDR_CODEC, HDRImages, read_hdr, merge_capture
    ingest: Ingest kernels: raw mosaic frames -> linear analyzer images -> one HDR image per view (DESIGN §2, §3)
        CELL, DEFAULT_SATURATION, HDR_WEIGHT_FLOOR, HDR_WEIGHT_WINDOW, GUIDE_FLOOR, IngestError, black_level_map,
        rawpy_black_level, linearize, analyzer_phases, DemosaicPlan, make_demosaic_plan, analyzer_cells, demosaic,
        apply_color_matrix, output_intrinsics, source_positions, RemapTable, make_remap, remap, IngestPlan,
        make_ingest_plan, process_frame, analyzer_plan, develop, hdr_weight, merge_hdr
    linearize: Linearize a capture's raw frames (DESIGN §2 linearize; docs/ingest.md): black and white level,
      saturation mask, demosaic into the four analyzer images, colour matrix, undistortion, one store for all frames
      (:func:`linearize_capture`); a bad frame stops with its file and row, or is left out with ``bad_frames: skip``
        BLACK_LEVEL_SOURCES, BAD_FRAME_POLICIES, linearize_capture
    mitsuba_capture: An independent renderer for synthetic captures: Mitsuba 3's ``pplastic`` under the rig's
      polarized flash
        MITSUBA_VARIANTS, POLARIZER_OFFSET_M, POLARIZER_HALF_SIZE_M, MAX_DEPTH, ALBEDO_ATTRIBUTE, PPlasticError,
        mitsuba_available, choose_variant, PPlasticMaterial, pplastic_materials, mitsuba_camera, MitsubaResult,
        MitsubaRenderer, render_in_subprocess
    mosaic: The sensor mosaic: which analyzer angle and which colour each raw pixel sees
        COLOR_LAYOUTS, MosaicError, MosaicLayout, mosaic_layout
    reader: Reading a capture folder (:func:`read_capture` -> :class:`Capture`) and its raw frames (DNG and camera
      RAW with rawpy, 16-bit TIFF/PNG as they are) as (H, W) mosaics in raw units
        Capture, read_capture, read_raw_file, read_raw_frame
    scenes: Procedural test scenes with known ground truth (no downloads) and handheld camera orbits
        SCENES, DEVICE_WIDTH_PX, DEVICE_FX_PX, SPHERE_IOR_ETAS, Material, DEMO_MATERIALS, DEMO_FINE_MATERIALS,
        Scene, icosphere, random_unit_vectors, cellular, bump, FEATHER_RELIEF_M, feather_relief, TINY_FLASH_POWER,
        TINY_BUMPS, TINY_BUMP_WIDTH_RAD, TINY_MATERIALS, COW_PATCH_ALBEDO, PPLASTIC_SET_MATERIALS, build_scene,
        device_intrinsics, look_at_rotation, handheld_orbit
    sensor: Sensor simulation: the IMX250MYR colour-polarization mosaic (DESIGN §3) from rendered analyzer images
        IMX250_POLARIZER_LAYOUT, DEFAULT_COLOR_MATRIX, SRGB_LUMINANCE, SensorModel, sensor_from_device,
        camera_rgb_from_srgb, mosaic_sample, sensor_mosaic, sensor_colors, simulate_raw
    synthetic: Synthetic captures with known truth (DESIGN §6; ``sellip synth``): a procedural scene rendered with
      the full pBRDF under the polarized flash on a handheld orbit, through the sensor simulator (mosaic, noise,
      quantization) into raw files, frames.csv, capture.yaml, poses.csv and the ground-truth model
      (:func:`synthesize_capture`)
        FLASH_LEVELS, FLASH_POSITION_CAM, RENDERERS, EXPOSURE_S, synthesize_capture
    tables: frames.csv and poses.csv (DESIGN §3): pandera schemas and validation that names the file, row and column
      of every problem
        FRAMES_SCHEMA, POSES_SCHEMA, validate_frames, validate_poses
    writer: Writing a capture folder (synthetic captures, tests): raw frames as DNG/TIFF/PNG, frames.csv,
      capture.yaml, poses.csv, under a temporary name and then renamed
        write_raw_file, RAW_FORMATS, DNG_MIN_SIZE, CaptureWriter, yaml_safe, write_capture

See docs/architecture.md for what this package owns and what it may import.
"""

from sellip._exports import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "assemble": ("RAW_SUFFIXES", "FIELDS", "AssembleError", "parse_pattern", "flash_level", "frames_from_pattern",
           "frames_from_csv", "assemble_capture"),
    "capture_yaml": ("CONFIG_SCHEMA", "MAX_FIELD_DEG", "validate_config"),
    "checks": ("DISTANCE_TOLERANCE", "UNIT_MATCH", "PoseUnitsError", "camera_distances", "likely_unit",
           "check_pose_units"),
    "files": ("CAPTURE_YAML", "FRAMES_CSV", "POSES_CSV", "RAW_DIR", "GROUND_TRUTH_DIR", "RAWPY_SUFFIXES",
           "TIFF_SUFFIXES", "PNG_SUFFIXES", "FRAME_COLUMNS", "POSE_COLUMNS", "CaptureError", "MissingFileError",
           "ConfigError", "UnknownLayoutError", "FramesError", "DuplicateFrameError", "FlashLevelError",
           "PosesError", "ViewWithoutFramesError", "RawFrameError", "GROUND_TRUTH_MESH", "MAX_LISTED_PROBLEMS",
           "more_problems"),
    "hdr": ("UNITS", "HDR_CODEC", "HDRImages", "read_hdr", "merge_capture"),
    "ingest": ("CELL", "DEFAULT_SATURATION", "HDR_WEIGHT_FLOOR", "HDR_WEIGHT_WINDOW", "GUIDE_FLOOR", "IngestError",
           "black_level_map", "rawpy_black_level", "linearize", "analyzer_phases", "DemosaicPlan",
           "make_demosaic_plan", "analyzer_cells", "demosaic", "apply_color_matrix", "output_intrinsics",
           "source_positions", "RemapTable", "make_remap", "remap", "IngestPlan", "make_ingest_plan",
           "process_frame", "analyzer_plan", "develop", "hdr_weight", "merge_hdr"),
    "linearize": ("BLACK_LEVEL_SOURCES", "BAD_FRAME_POLICIES", "linearize_capture"),
    "mitsuba_capture": ("MITSUBA_VARIANTS", "POLARIZER_OFFSET_M", "POLARIZER_HALF_SIZE_M", "MAX_DEPTH",
           "ALBEDO_ATTRIBUTE", "PPlasticError", "mitsuba_available", "choose_variant", "PPlasticMaterial",
           "pplastic_materials",
           "mitsuba_camera", "MitsubaResult", "MitsubaRenderer", "render_in_subprocess"),
    "mosaic": ("COLOR_LAYOUTS", "MosaicError", "MosaicLayout", "mosaic_layout"),
    "reader": ("Capture", "read_capture", "read_raw_file", "read_raw_frame"),
    "scenes": ("SCENES", "DEVICE_WIDTH_PX", "DEVICE_FX_PX", "SPHERE_IOR_ETAS", "Material", "DEMO_MATERIALS",
           "DEMO_FINE_MATERIALS", "Scene", "icosphere", "random_unit_vectors", "cellular", "bump",
           "FEATHER_RELIEF_M", "feather_relief", "TINY_FLASH_POWER", "TINY_BUMPS", "TINY_BUMP_WIDTH_RAD",
           "TINY_MATERIALS", "COW_PATCH_ALBEDO", "PPLASTIC_SET_MATERIALS", "build_scene", "device_intrinsics",
           "look_at_rotation", "handheld_orbit"),
    "sensor": ("IMX250_POLARIZER_LAYOUT", "DEFAULT_COLOR_MATRIX", "SRGB_LUMINANCE", "SensorModel",
           "sensor_from_device", "camera_rgb_from_srgb", "mosaic_sample", "sensor_mosaic", "sensor_colors",
           "simulate_raw"),
    "synthetic": ("FLASH_LEVELS", "FLASH_POSITION_CAM", "RENDERERS", "EXPOSURE_S", "synthesize_capture"),
    "tables": ("FRAMES_SCHEMA", "POSES_SCHEMA", "validate_frames", "validate_poses"),
    "writer": ("write_raw_file", "RAW_FORMATS", "DNG_MIN_SIZE", "CaptureWriter", "yaml_safe", "write_capture"),
})
