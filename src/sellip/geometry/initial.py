"""The initial mesh (docs/design.md §2 mesh_init; rule ``init_mesh``): the visual hull fused with SfM's sparse
points, or multi-view stereo points, or a mesh the user supplies (a scan), checked against the silhouettes
(:func:`make_initial_mesh`).
"""

from __future__ import annotations

import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from sellip.geometry import hull as geometry_hull
from sellip.geometry import scan as geometry_scan
from sellip.geometry import sfm
from sellip.geometry.cameras import diffuse_view, intrinsics_matrix, read_cameras, view_masks
from sellip.jobs import atomic_file, write_text
from sellip.model.ply import read_ply, write_ply

log = logging.getLogger(__name__)





MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off")
"""Mesh files ``init.mode: mesh`` reads (open3d); PLY and OBJ are the documented ones."""



class InitMeshError(RuntimeError):
    """The initial mesh cannot be built with the given inputs (e.g. mvs without CUDA, a supplied mesh that does
    not fit the silhouettes)."""



def read_user_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """A triangle mesh file (open3d): vertices (V, 3) float64, faces (F, 3) int64 and the file's vertex normals
    (V, 3) or None. Vertices at the same position are merged (a triangle soup, as STL and some PLY writers
    store it, would otherwise fall apart into single triangles); degenerate and duplicated faces are dropped.
    Raises InitMeshError naming the file when it is missing, unreadable, or has no triangles."""
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise InitMeshError(f"{path}: the mesh file of init.mode 'mesh' (init.mesh_path) does not exist")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InitMeshError(f"{path}: not a mesh file that init.mode 'mesh' reads ({', '.join(MESH_SUFFIXES)})")
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.vertices) == 0:
        raise InitMeshError(f"{path}: cannot be read as a triangle mesh (open3d finds no vertices: damaged, or not a "
                            f"{path.suffix.lstrip('.').upper()} file)")
    if len(mesh.triangles) == 0:
        raise InitMeshError(f"{path}: has {len(mesh.vertices)} vertices but no triangles (a point cloud?); "
                            "init.mode 'mesh' needs a triangle mesh")
    mesh.remove_duplicated_vertices()
    mesh.remove_degenerate_triangles()
    mesh.remove_duplicated_triangles()
    mesh.remove_unreferenced_vertices()
    vertices, faces = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.triangles, np.int64)
    if len(faces) == 0 or not np.isfinite(vertices).all():
        raise InitMeshError(f"{path}: has no usable triangles (all degenerate) or non-finite vertex coordinates")
    normals = np.asarray(mesh.vertex_normals, np.float64) if mesh.has_vertex_normals() else None
    if normals is not None and not (np.isfinite(normals).all() and np.linalg.norm(normals, axis=1).mean() > 0.5):
        normals = None  # zeros or NaN: no orientation to learn from
    return vertices, faces, normals



def sparse_observations(sfm_dir: Path, view_ids: list[str]) -> tuple[np.ndarray, list[np.ndarray], np.ndarray] | None:
    """SfM points (P, 3), their observing view indices (into ``view_ids``) and errors (P,) in px of the
    hdr images, from ``sfm_dir/sparse`` (None when the folder has no model, e.g. sfm.mode known)."""
    import pycolmap

    if not (sfm_dir / "sparse" / "points3D.bin").is_file():
        return None
    report = json.loads((sfm_dir / "report.json").read_text())
    upscale = float(report.get("upscale", 1))
    index_of_view = {v: i for i, v in enumerate(view_ids)}
    reconstruction = pycolmap.Reconstruction(sfm_dir / "sparse")
    view_of_image = {image_id: index_of_view.get(report["image_names"][image.name])
                     for image_id, image in reconstruction.images.items()}
    points, views, errors = [], [], []
    for point in reconstruction.points3D.values():
        observers = {view_of_image[e.image_id] for e in point.track.elements} - {None}
        if observers:
            points.append(point.xyz)
            views.append(np.array(sorted(observers)))
            errors.append(point.error / upscale)
    return np.asarray(points, np.float64).reshape(-1, 3), views, np.asarray(errors)



def mvs_points(hdr, sfm_dir: Path, view_ids: list[str], masks: np.ndarray, threads: int) -> tuple[np.ndarray,
                                                                                                  np.ndarray]:
    """Oriented points (N, 3), (N, 3) from COLMAP PatchMatch stereo + fusion on the SfM model (CUDA only)."""
    import pycolmap

    if not pycolmap.has_cuda:
        raise InitMeshError("init.mode 'mvs' needs pycolmap built with CUDA (pycolmap.has_cuda is False); "
                            "use init.mode 'hull' (CPU)")
    if not (sfm_dir / "sparse" / "points3D.bin").is_file():
        raise InitMeshError(f"init.mode 'mvs' needs an SfM model in {sfm_dir}/sparse; run with sfm.mode sfm or verify")
    report = json.loads((sfm_dir / "report.json").read_text())
    upscale = int(report.get("upscale", 1))
    index_of_view = {v: i for i, v in enumerate(view_ids)}
    with tempfile.TemporaryDirectory(prefix="sellip-mvs-") as work:
        work = Path(work)
        image_dir = work / "images"
        image_dir.mkdir()
        import imageio.v3 as iio

        for name, view in report["image_names"].items():
            if view in index_of_view:
                diffuse, _ = diffuse_view(hdr, hdr.view_ids.index(view))
                image, _ = sfm.feature_image(diffuse, masks[index_of_view[view]], upscale)
                iio.imwrite(image_dir / name, image)
        pycolmap.undistort_images(work / "dense", sfm_dir / "sparse", image_dir, num_threads=threads)
        pycolmap.patch_match_stereo(work / "dense")
        pycolmap.stereo_fusion(work / "fused.ply", work / "dense", output_type="PLY")
        vertex, _ = read_ply(work / "fused.ply")
    points = np.stack([vertex[k] for k in ("x", "y", "z")], axis=1).astype(np.float64)
    normals = np.stack([vertex[k] for k in ("nx", "ny", "nz")], axis=1).astype(np.float64)
    return points, normals



CAMERAS_ADVICE = ("the cameras do not describe these photographs. Check capture.yaml's camera.fx, fy, cx, cy (raw "
                  "pixels) and distortion, that poses.csv is cam_from_world (COLMAP's convention, not the camera's "
                  "pose in the world) and is this capture's, and the silhouette threshold (silhouette.threshold)")
"""What to check when the silhouettes and the cameras disagree about the object (docs/reliability.md)."""

COVERAGE_STOP = 0.6
"""The stage stops when the visual hull's projection covers less than this fraction of the silhouette in half of the
views (:func:`sellip.geometry.hull.silhouette_coverage`): a hull carved by cameras that are not the capture's is
the small part every view's cone shares. Measured medians: 1.000 on every sphere of the stability suite and the
demo, 0.89-0.90 on the cow (its black patches below the silhouette level), 0.82 / 0.51 / 0.23 with the tiny sphere's
cameras moved sideways by 1 / 2 / 3 cm at 0.9 m (docs/reliability.md)."""

DISAGREEMENT_STOP = 0.25
"""The stage stops when, in half of the views or more, more than this fraction of the initial mesh (the hull or the
scan) projects outside the silhouette: the cameras cannot be this capture's (a warning names single views above
``disagreement_warn``). Measured medians: 0.002-0.007 on every sphere of the stability suite, 0.024-0.027 on the
cow, whose black patches fall below the silhouette level (its worst view 0.24; docs/reliability.md)."""


OUTLIER_VIEW_Z = geometry_hull.InitMeshOptions.outlier_view_z
"""The declared default of config ``init.outlier_view_z`` (:class:`sellip.geometry.hull.InitMeshOptions`): a view
whose silhouette disagreement with the other views' hull
(:attr:`sellip.geometry.hull.Carving.others_disagreement`; with init.mode mesh, with the scan) lies more than this
many robust standard deviations (1.4826 x the median absolute deviation, at least OUTLIER_SPREAD_FLOOR) above the
views' median, and above ``disagreement_warn``, is named as a likely swapped or misplaced view."""

OUTLIER_SPREAD_FLOOR = 0.01
"""The robust spread of the views' disagreements is taken as at least this (a fraction of the mesh): on a sphere
every view agrees to 0.002-0.007, and a spread near 0 would make any small difference an outlier."""


def outlier_views(disagreement: np.ndarray, z: float = OUTLIER_VIEW_Z, minimum: float = 0.05) -> np.ndarray:
    """(V,) bool: views whose disagreement (V,) (fraction of the mesh outside their silhouette) is an outlier among
    the views: above the median by more than ``z`` robust standard deviations (1.4826 MAD, at least
    OUTLIER_SPREAD_FLOOR) and above ``minimum``. Fewer than 4 views: none (no rest to compare with)."""
    values = np.asarray(disagreement, np.float64)
    if len(values) < 4:
        return np.zeros(len(values), bool)
    median = float(np.median(values))
    spread = max(1.4826 * float(np.median(np.abs(values - median))), OUTLIER_SPREAD_FLOOR)
    return ((values - median) / spread > z) & (values > minimum)


def warn_outlier_views(view_ids: list[str], disagreement: np.ndarray, against: str, z: float = OUTLIER_VIEW_Z,
                       minimum: float = 0.05) -> list[str]:
    """The ids of the :func:`outlier_views` of ``disagreement`` (V,), named in a WARNING (the run's summary) as
    likely swapped or misplaced views; ``against``: what they were compared with, for the message."""
    outliers = [v for v, bad in zip(view_ids, outlier_views(disagreement, z, minimum)) if bad]
    if outliers:
        log.warning("view(s) %s: the silhouette disagrees with %s far more than the other views do (%s of it "
                    "outside the mask, against a median %.0f%%; init.outlier_view_z %g): a swapped or misplaced "
                    "view? Check these views' rows in frames.csv (the files) and poses.csv (their poses)",
                    ", ".join(repr(v) for v in outliers[:30]), against, ", ".join(
                        f"{100 * disagreement[view_ids.index(v)]:.0f}%" for v in outliers[:30]),
                    100 * float(np.median(disagreement)), z)
    return outliers


def make_initial_mesh(hdr_path: str | Path, cameras_path: str | Path, sfm_dir: str | Path, output: str | Path,
              options: geometry_hull.InitMeshOptions = geometry_hull.InitMeshOptions(),
              mask_options: dict | None = None, disagreement_warn: float = 0.05,
              mesh_path: str | Path | None = None) -> dict:
    """Run the stage (see the module docstring); returns the report written beside the mesh.

    mesh_path: the mesh of mode ``mesh`` (required there, ignored otherwise), as given (the workflow resolves
    ``init.mesh_path`` against the capture folder). options: config ``init`` (``options.mode``: how the mesh is made;
    ``options.outlier_view_z``: :func:`warn_outlier_views`).
    Long: the checks of the silhouettes (coverage, disagreement, outlier views) share the mesh and the report.
    """
    from sellip.capture.hdr import read_hdr

    started = time.perf_counter()
    mode = options.mode
    if mode == "mesh":
        if not mesh_path:
            raise InitMeshError("init.mode 'mesh' needs the mesh file: set init.mesh_path (--mesh-path)")
        user_mesh = read_user_mesh(mesh_path)  # before the silhouettes: a bad file fails fast
    elif mesh_path:
        log.warning("init.mode %r: the mesh %s is not used (init.mesh_path is read with init.mode 'mesh' only)",
                    mode, mesh_path)
    hdr = read_hdr(hdr_path)
    view_ids, rotations, translations = read_cameras(cameras_path)
    unknown = [v for v in view_ids if v not in hdr.view_ids]
    if unknown:
        raise InitMeshError(f"{cameras_path}: views {unknown[:10]} are not in {hdr_path}")
    all_masks = view_masks(hdr, mask_options or {})
    masks = all_masks[[hdr.view_ids.index(v) for v in view_ids]]
    intrinsics = intrinsics_matrix(hdr.intrinsics)
    if mode == "mesh":
        vertices, faces, normals = user_mesh
        mesh = geometry_scan.user_initial_mesh(vertices, faces, masks, intrinsics, rotations, translations, options,
                                          normals=normals)
        if mesh.check.problems:
            raise InitMeshError(f"{mesh_path}: the mesh (init.mesh_path) does not fit the silhouettes of the "
                                f"{len(view_ids)} views of {cameras_path}: " + "; ".join(mesh.check.problems))
        disagreement, against, advice = 1.0 - mesh.check.inside_fraction, "the supplied mesh", ""
        extra_report = {"mesh_path": str(mesh_path), "check": mesh.check.stats(view_ids)}
    else:
        sfm_dir = Path(sfm_dir)
        sparse = sparse_observations(sfm_dir, view_ids)
        extra = mvs_points(hdr, sfm_dir, view_ids, masks, options.threads) if mode == "mvs" else None
        try:
            mesh = geometry_hull.hull_mesh(masks, intrinsics, rotations, translations, options,
                                              *(sparse if sparse is not None else (None, None, None)),
                                              extra_points=extra)
        except geometry_hull.EmptyHullError as error:
            raise InitMeshError(f"{cameras_path}: {error}: " + CAMERAS_ADVICE) from None
        disagreement, against = mesh.carving.disagreement, "the visual hull"
        advice = f"; min_inside_fraction {options.min_inside_fraction:.2f} tolerates a few bad masks"
        coverage = geometry_hull.silhouette_coverage(mesh.vertices, mesh.faces, masks, intrinsics, rotations,
                                                     translations)
        extra_report = {"silhouette_coverage": {v: float(c) for v, c in zip(view_ids, coverage)}}
        if np.median(coverage) < COVERAGE_STOP:
            raise InitMeshError(
                f"{cameras_path}: the visual hull covers a median {100 * np.median(coverage):.0f}% of the "
                f"silhouettes (worst {100 * coverage.min():.0f}%, view {view_ids[int(np.argmin(coverage))]}): the "
                "views' cones barely overlap, so " + CAMERAS_ADVICE)

    disagreeing = [v for v, d in zip(view_ids, disagreement) if d > disagreement_warn]
    if np.median(disagreement) > DISAGREEMENT_STOP:
        raise InitMeshError(
            f"{cameras_path}: the silhouettes disagree with {against} in {len(disagreeing)} of {len(view_ids)} views "
            f"(in half of them more than {100 * np.median(disagreement):.0f}% of it outside the mask): "
            + CAMERAS_ADVICE)
    if disagreeing:
        log.warning("%d of %d silhouettes disagree with %s (more than %.0f%% of it outside the mask): %s. Check "
                    "the poses of these views or the silhouette threshold (silhouette.threshold)%s.", len(disagreeing),
                    len(view_ids), against, 100 * disagreement_warn, ", ".join(disagreeing[:30]), advice)
    others = (mesh.carving.others_disagreement, "the other views' hull") if mode != "mesh" else (disagreement, against)
    outliers = warn_outlier_views(view_ids, *others, options.outlier_view_z, disagreement_warn)
    report = dict(mesh.stats, mode=mode, views=len(view_ids), **extra_report, outlier_views=outliers,
                  others_disagreement={v: float(d) for v, d in zip(view_ids, others[0])},
                  silhouette_disagreement={v: float(d) for v, d in zip(view_ids, disagreement)},
                  disagreeing_views=disagreeing, total_s=time.perf_counter() - started)
    output = Path(output)
    vertices, normals = mesh.vertices.astype(np.float32), mesh.normals.astype(np.float32)
    write_text(json.dumps(report, indent=2), output.with_suffix(".json"))
    with atomic_file(output) as tmp:
        write_ply(tmp, {"x": vertices[:, 0], "y": vertices[:, 1], "z": vertices[:, 2],
                        "nx": normals[:, 0], "ny": normals[:, 1], "nz": normals[:, 2]}, mesh.faces)
    log.info("initial mesh: %d vertices, %d faces (%s, %.1f s)", len(vertices), len(mesh.faces), mode,
             report["total_s"])
    return report
