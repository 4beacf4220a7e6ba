"""Cameras, silhouettes and meshes (above model; beside capture, which it may use).

Sim(3) alignment and pose errors, the cameras table, the poses job (known, SfM with pycolmap, verify),
silhouettes above the noise floor, the visual hull and the initial mesh, a scan checked against the
silhouettes, mesh utilities, and the geometry update (normal integration held by the silhouettes).
Conventions: metres; poses are COLMAP cam_from_world; OpenCV intrinsics, pixel centres at integers.

Modules and what they export (each name is importable from here too)::

    alignment: Sim(3) alignment of camera sets and pose errors (docs/design.md §8: SfM poses are compared after a
      similarity alignment)
        Similarity, umeyama, align_cameras, refine_to_surface, pose_errors
    cameras: The cameras table ``cameras.csv`` (poses.csv's columns: COLMAP cam_from_world) and cameras built from it:
      its reader and writer, the intrinsics matrix of capture.yaml's camera, a view's camera at the HDR images'
      resolution (half the raw mosaic), the diffuse image and silhouette masks a view gives SfM and the hull
        CamerasError, write_cameras, read_cameras, diffuse_view, intrinsics_matrix, hdr_camera, load_cameras
    hull: The visual hull and the initial mesh (docs/design.md §2 mesh_init): voxel carving from the silhouettes, the
      surface points of the occupancy, fusion with SfM's sparse points, screened Poisson at a depth and remeshing to a
      vertex count
        visual_hull, surface_points, INIT_MODES, InitMeshOptions, hull_mesh
    initial: The initial mesh (docs/design.md §2 mesh_init; rule ``init_mesh``): the visual hull fused with SfM's sparse
      points, or multi-view stereo points, or a mesh the user supplies (a scan), checked against the silhouettes
      (:func:`make_initial_mesh`)
        InitMeshError, make_initial_mesh, OUTLIER_VIEW_Z, outlier_views
    meshes: Triangle-mesh utilities: surface samples and mesh-to-mesh distances (docs/design.md §8 Chamfer and
      Hausdorff), point normals, screened Poisson, the largest component, isotropic remeshing to a vertex count, vertex
      normals, edges
        angular_error_deg, surface_samples, mesh_distances, poisson_surface, depth_vertex_count, remesh_to_count,
        vertex_normals, blend_normals
    pose_refinement: Camera poses refined against the object (issue #36 item 4; rule ``refine_poses``; docs/geometry.md,
      "Poses refined against the object")
        PoseRefinementSettings, moved_pose, pose_change, align_pose, refine_view
    poses: The poses of a capture (docs/design.md §2 sfm; rule ``run_sfm``): known (poses.csv), SfM (pycolmap), or SfM
      verified against poses.csv; SfM poses scaled to ``scene.distance_m``; ``cameras.csv`` and the comparison with
      known poses (rotation and centre errors after a similarity alignment)
        compare_to_known, solve_poses
    scan: A mesh the user supplies (``init.mode: mesh``, a scan): oriented outward, resampled to a vertex count and
      checked against the silhouettes (scale, units, placement), with a message that names the likely problem
        UNIT_SIZES, resample_to_count, check_against_silhouettes
    sfm: Structure from motion with pycolmap on the diffuse images I_d = 2 I90 (docs/design.md §2 sfm, §3 notes)
        POSE_MODES, MATCHING, RegistrationError, SfmOptions, SfmResult, tone_map, feature_upscale, feature_image,
        scale_intrinsics,
        match_pairs_by_retrieval, run_sfm, result_from_reconstruction, metric_normalization, transform_result,
        check_registration
    silhouettes: Silhouettes of the object in the HDR views: the level above the background's noise floor, the masks,
      and signed distances to their boundary (to a fraction of a pixel)
        background_noise, DEFAULT_SILHOUETTE, silhouette_level, silhouette_masks, signed_distance, Silhouette,
        boundary_distance, SilhouetteOptions
    update: The geometry update (docs/design.md §2, docs/geometry_update.md): the surface moved to agree with the
      confident fitted normals by normal integration (a sparse least-squares problem), held by the photographs'
      silhouettes
        SilhouetteConstraints, silhouette_constraints, refine_from_normals

See docs/architecture.md for what this package owns and what it may import.
"""

from sellip._exports import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "alignment": ("Similarity", "umeyama", "align_cameras", "refine_to_surface", "pose_errors"),
    "cameras": ("CamerasError", "write_cameras", "read_cameras", "diffuse_view", "intrinsics_matrix", "hdr_camera",
           "load_cameras"),
    "hull": ("visual_hull", "surface_points", "INIT_MODES", "InitMeshOptions", "hull_mesh"),
    "initial": ("InitMeshError", "make_initial_mesh", "OUTLIER_VIEW_Z", "outlier_views"),
    "meshes": ("angular_error_deg", "surface_samples", "mesh_distances", "poisson_surface", "depth_vertex_count",
           "remesh_to_count", "vertex_normals", "blend_normals", "SurfaceDefects", "surface_defects"),
    "pose_refinement": ("PoseRefinementSettings", "moved_pose", "pose_change", "align_pose", "refine_view"),
    "poses": ("compare_to_known", "solve_poses"),
    "scan": ("UNIT_SIZES", "resample_to_count", "check_against_silhouettes"),
    "sfm": ("POSE_MODES", "MATCHING", "RegistrationError", "SfmOptions", "SfmResult", "tone_map", "feature_upscale",
           "feature_image", "scale_intrinsics", "match_pairs_by_retrieval", "run_sfm", "result_from_reconstruction",
           "metric_normalization", "transform_result", "check_registration"),
    "silhouettes": ("background_noise", "DEFAULT_SILHOUETTE", "silhouette_level", "silhouette_masks",
           "signed_distance", "Silhouette", "boundary_distance", "SilhouetteOptions"),
    "update": ("SilhouetteConstraints", "silhouette_constraints", "refine_from_normals", "step_without_folds"),
})
