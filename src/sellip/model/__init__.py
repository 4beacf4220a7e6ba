"""The physics and the model's records (the bottom floor: imports no other sellip package).

Conventions (frames, Stokes, analyzers), Stokes/Mueller algebra, Fresnel, GGX, the three-lobe pBRDF, the
parameter records and the params.zarr store, the PLY model file, and the forward renderer.

Modules and what they export (each name is importable from here too)::

    conventions: The conventions every stage shares, stated and implemented once (DESIGN §3)
        ANALYZER_ANGLES_DEG, analyzer_intensity, stokes_to_analyzers, analyzers_to_stokes,
        observations_from_analyzers, camera_center, camera_right, camera_up, camera_forward, camera_to_world_point,
        quaternion_to_rotation, rotation_to_quaternion
    fresnel: Fresnel terms of a smooth dielectric interface between air and index ``eta`` (JAX, batched)
        FresnelTerms, fresnel, brewster_angle, diffuse_dop, reflection_mueller, transmission_mueller
    microfacet: GGX microfacet distribution and separable Smith shadowing (JAX, batched)
        ggx_d, smith_g1, smith_g
    params: Per-vertex parameter stores (``params.zarr``) and carrying parameters between meshes
        PARAM_FIELDS, EXTRA_FIELDS, MODEL_NAMES, ParamsError, fill_from_neighbours, same_vertices, transfer_nearest,
        write_params, read_params, params_from
    pbrdf: The three-lobe polarimetric BRDF of Hwang et al
        PBRDFParams, Observations, ViewFrames, view_frames, SurfaceTerms, surface_terms, reflection_stokes,
        diffuse_stokes, full_mueller, lobe_stokes, lobe_factor, full_stokes, normal_azimuth_terms,
        coaxial_observations
    ply: PLY meshes with per-vertex parameters (DESIGN §4 ``final/model.ply``): a small binary PLY writer and
      reader, and the model's vertex properties (x y z nx ny nz eta rho_d_rgb rho_s sigma_s rho_ss_rgb sigma_ss,
      float32)
        PlyError, MODEL_VERTEX_PROPERTIES, write_ply, read_ply, write_param_mesh, read_param_mesh
    polar: Stokes/Mueller algebra (JAX, batched, channels last)
        safe_sqrt, safe_normalize, rotator_from_cos_sin, rotator, linear_polarizer, depolarizer, dolp, aolp,
        frame_rotation_terms, frame_rotation, rotate_linear_stokes, frame_x_axis, orthogonal_x_axis
    render: Forward renderer: a mesh with per-vertex pBRDF parameters, seen by a pinhole camera under a polarized
      point light
        PARAM_CHANNELS, SHADING_CHUNK, FLASH_STOKES, SHADOW_EPSILON_M, ParamMesh, unpack_params, Camera, Light,
        flash_light, distort_normalized, undistort_normalized, subpixel_offsets, pixel_rays, coverage_masks,
        RenderResult, Renderer, render_stokes

See docs/architecture.md for what this package owns and what it may import.
"""

from sellip._exports import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "conventions": ("ANALYZER_ANGLES_DEG", "analyzer_intensity", "stokes_to_analyzers", "analyzers_to_stokes",
           "observations_from_analyzers", "camera_center", "camera_right", "camera_up", "camera_forward",
           "camera_to_world_point", "quaternion_to_rotation", "rotation_to_quaternion"),
    "fresnel": ("FresnelTerms", "fresnel", "brewster_angle", "diffuse_dop", "reflection_mueller",
                "transmission_mueller"),
    "microfacet": ("ggx_d", "smith_g1", "smith_g"),
    "params": ("PARAM_FIELDS", "EXTRA_FIELDS", "MODEL_NAMES", "ParamsError", "fill_from_neighbours", "same_vertices",
           "transfer_nearest", "write_params", "read_params", "params_from"),
    "pbrdf": ("PBRDFParams", "Observations", "ViewFrames", "view_frames", "SurfaceTerms", "surface_terms",
           "reflection_stokes", "diffuse_stokes", "full_mueller", "lobe_stokes", "lobe_factor", "full_stokes",
           "normal_azimuth_terms", "coaxial_observations"),
    "ply": ("PlyError", "MODEL_VERTEX_PROPERTIES", "write_ply", "read_ply", "write_param_mesh", "read_param_mesh"),
    "polar": ("safe_sqrt", "safe_normalize", "rotator_from_cos_sin", "rotator", "linear_polarizer", "depolarizer",
           "dolp", "aolp", "frame_rotation_terms", "frame_rotation", "rotate_linear_stokes", "frame_x_axis",
           "orthogonal_x_axis"),
    "render": ("PARAM_CHANNELS", "SHADING_CHUNK", "FLASH_STOKES", "SHADOW_EPSILON_M", "ParamMesh", "unpack_params",
           "Camera", "Light", "flash_light", "distort_normalized", "undistort_normalized", "subpixel_offsets",
           "pixel_rays", "coverage_masks", "RenderResult", "Renderer", "render_stokes"),
})
