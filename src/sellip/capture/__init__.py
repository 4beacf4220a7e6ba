"""A capture: its format, its sensor and its ingest (above model).

The capture folder (docs/design.md §3: capture.yaml, frames.csv, poses.csv, raw frames) read, validated and
written; the polarization mosaic and the sensor simulator; linearize, demosaic and the HDR merge into hdr.zarr;
synthetic scenes and synthetic captures with known truth.

Modules and what they export (each name is importable from here too)::

    assemble: A capture folder (docs/design.md §3) from a folder of raw frames and a calibrated device.yaml (``sellip
      capture new``)
        parse_pattern, flash_level, assemble_capture, check_flash_fired
    capture_yaml: capture.yaml (docs/design.md §3): its JSON schema and :func:`validate_config`, which names the key,
      what was expected and what was found
        CONFIG_SCHEMA, schema_problem, validate_config
    checks: Unit checks of a capture's numbers against each other (issue #38): lengths that are off by a factor of 1000
      must not pass silently
        PoseUnitsError, camera_distances, check_pose_units, SamePoseError
    files: The capture folder's file names and columns (docs/design.md §3), and the errors every reader raises
      (:class:`CaptureError` and its kinds: each names the file, and where it applies the row, column or key)
        CAPTURE_YAML, FRAMES_CSV, POSES_CSV, POSE_COLUMNS, CaptureError, MissingFileError, ConfigError,
        UnknownLayoutError, FramesError, DuplicateFrameError, FlashLevelError, PosesError, ViewWithoutFramesError,
        RawFrameError, GROUND_TRUTH_MESH, MAX_LISTED_PROBLEMS
    hdr: The HDR store ``hdr.zarr`` (docs/design.md §2 hdr_merge): one HDR image per view and analyzer (I0, I45, I90,
      I135, RGB, float32, relative radiance) and its valid mask, merged from a view's flash levels
      (:func:`merge_capture`), and its reader (:func:`read_hdr` -> :class:`HDRImages`)
        HDR_CODEC, read_hdr, merge_capture
    ingest: Ingest kernels: raw mosaic frames -> linear analyzer images -> one HDR image per view (docs/design.md §2,
      §3)
        BLACK_LEVEL_SOURCES, BAD_FRAME_POLICIES, IngestSettings, CELL, DEFAULT_SATURATION, HDR_WEIGHT_FLOOR,
        IngestError, black_level_map, rawpy_black_level, linearize, make_demosaic_plan, demosaic, apply_color_matrix,
        output_intrinsics, source_positions, remap, make_ingest_plan, process_frame, analyzer_plan, develop,
        hdr_weight, merge_hdr, FLASH_RATIO_TOLERANCE, brightness_ratios, mislabelled_frames
    linearize: Linearize a capture's raw frames (docs/design.md §2 linearize; docs/ingest.md): black and white level,
      saturation mask, demosaic into the four analyzer images, colour matrix, undistortion, one store for all frames
      (:func:`linearize_capture`); a bad frame stops with its file and row, or is left out with ``bad_frames: skip``
        linearize_capture
    mitsuba_capture: An independent renderer for synthetic captures: Mitsuba 3's ``pplastic`` under the rig's polarized
      flash
        PPlasticError, mitsuba_available, choose_variant, pplastic_materials, mesh_shape, flash_scene, render_stokes,
        render_in_subprocess
    mosaic: The sensor mosaic: which analyzer angle and which colour each raw pixel sees
        mosaic_layout
    reader: Reading a capture folder (:func:`read_capture` -> :class:`Capture`) and its raw frames (DNG and camera RAW
      with rawpy, 16-bit TIFF/PNG as they are) as (H, W) mosaics in raw units
        read_capture, read_raw_file, read_raw_frame, exposure_time, flash_fired
    scenes: Procedural test scenes with known ground truth (no downloads) and handheld camera orbits
        SCENES, DEVICE_WIDTH_PX, DEVICE_FX_PX, SPHERE_IOR_ETAS, icosphere, TINY_BUMPS, TINY_MATERIALS, build_scene,
        device_intrinsics, look_at_rotation, handheld_orbit, BOWL_AXIS, BOWL_DEPTH_M
    sensor: Sensor simulation: the IMX250MYR colour-polarization mosaic (docs/design.md §3) from rendered analyzer
      images
        DEFAULT_COLOR_MATRIX, SensorModel, sensor_from_device, camera_rgb_from_srgb, mosaic_sample, sensor_mosaic,
        sensor_colors, simulate_raw
    synthetic: Synthetic captures with known truth (docs/design.md §6; ``sellip synth``): a procedural scene rendered
      with the full pBRDF under the polarized flash on a handheld orbit, through the sensor simulator (mosaic, noise,
      quantization) into raw files, frames.csv, capture.yaml, poses.csv and the ground-truth model
      (:func:`synthesize_capture`)
        RENDERERS, DemoSettings, synthesize_capture, is_synthetic_folder
    tables: frames.csv and poses.csv (docs/design.md §3): pandera schemas and validation that names the file, row and
      column of every problem
        validate_poses
    writer: Writing a capture folder (synthetic captures, tests): raw frames as DNG/TIFF/PNG, frames.csv, capture.yaml,
      poses.csv, under a temporary name and then renamed
        write_raw_file, RAW_FORMATS, CaptureWriter, yaml_safe, write_capture

See docs/architecture.md for what this package owns and what it may import.
"""

from sellip._exports import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "assemble": ("parse_pattern", "flash_level", "assemble_capture", "check_flash_fired"),
    "capture_yaml": ("CONFIG_SCHEMA", "schema_problem", "validate_config"),
    "checks": ("PoseUnitsError", "camera_distances", "check_pose_units", "SamePoseError"),
    "files": ("CAPTURE_YAML", "FRAMES_CSV", "POSES_CSV", "POSE_COLUMNS", "CaptureError", "MissingFileError",
           "ConfigError", "UnknownLayoutError", "FramesError", "DuplicateFrameError", "FlashLevelError",
           "PosesError", "ViewWithoutFramesError", "RawFrameError", "GROUND_TRUTH_MESH", "MAX_LISTED_PROBLEMS"),
    "hdr": ("HDR_CODEC", "read_hdr", "merge_capture"),
    "ingest": ("BLACK_LEVEL_SOURCES", "BAD_FRAME_POLICIES", "IngestSettings", "CELL", "DEFAULT_SATURATION",
           "HDR_WEIGHT_FLOOR", "IngestError", "black_level_map", "rawpy_black_level", "linearize",
           "make_demosaic_plan", "demosaic", "apply_color_matrix", "output_intrinsics", "source_positions", "remap",
           "make_ingest_plan", "process_frame", "analyzer_plan", "develop", "hdr_weight", "merge_hdr",
           "FLASH_RATIO_TOLERANCE", "brightness_ratios", "mislabelled_frames"),
    "linearize": ("linearize_capture",),
    "mitsuba_capture": ("PPlasticError", "mitsuba_available", "choose_variant", "pplastic_materials", "mesh_shape",
                        "flash_scene", "render_stokes", "render_in_subprocess"),
    "mosaic": ("mosaic_layout",),
    "reader": ("read_capture", "read_raw_file", "read_raw_frame", "exposure_time", "flash_fired"),
    "scenes": ("SCENES", "DEVICE_WIDTH_PX", "DEVICE_FX_PX", "SPHERE_IOR_ETAS", "icosphere", "TINY_BUMPS",
           "TINY_MATERIALS", "build_scene", "device_intrinsics", "look_at_rotation", "handheld_orbit", "BOWL_AXIS",
           "BOWL_DEPTH_M"),
    "sensor": ("DEFAULT_COLOR_MATRIX", "SensorModel", "sensor_from_device", "camera_rgb_from_srgb", "mosaic_sample",
           "sensor_mosaic", "sensor_colors", "simulate_raw"),
    "synthetic": ("RENDERERS", "DemoSettings", "synthesize_capture", "is_synthetic_folder"),
    "tables": ("validate_poses",),
    "writer": ("write_raw_file", "RAW_FORMATS", "CaptureWriter", "yaml_safe", "write_capture"),
})
