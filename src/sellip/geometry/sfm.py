"""Structure from motion with pycolmap on the diffuse images I_d = 2 I90 (docs/design.md §2 sfm, §3 notes).

Public API::

    SfmOptions(...)                                   # matching strategy, features, thresholds
    SfmResult                                         # poses of every view (NaN if unregistered), sparse points
    tone_map(image, mask=None, percentile=99.5) -> (H, W) uint8
    feature_upscale(masks, object_px, max_upscale) -> int
    feature_image(image, mask, upscale=1) -> (image (sH, sW) uint8, mask (sH, sW) bool)
    scale_intrinsics(intrinsics, upscale) -> (3, 3)
    match_pairs_by_retrieval(descriptors, neighbours, overlap, words=256, seed=0) -> (M, 2) int
    run_sfm(images, masks, intrinsics, view_ids, work_dir, options) -> SfmResult
    result_from_reconstruction(reconstruction, view_ids, image_names) -> SfmResult
    metric_normalization(result, distance_m) -> Similarity
    transform_result(result, similarity) -> SfmResult
    check_registration(result, min_fraction) -> None   # raises RegistrationError
    RegistrationError

Pipeline (:func:`run_sfm`): the 8-bit images and the silhouette masks are written for COLMAP
(features only on the object: on flash photographs the dark background is noise); SIFT
extraction on CPU; matching exhaustive up to ``exhaustive_max_views`` views, above that the
pairs of a bag-of-words retrieval plus neighbours in capture order; incremental mapping with
the calibrated PINHOLE intrinsics held fixed unless ``refine_intrinsics``.

Intrinsics: sellip uses OpenCV's pixel convention (pixel centres at integer coordinates),
COLMAP puts the centre of the top-left pixel at (0.5, 0.5): the principal point given to
COLMAP is ``(cx + 0.5, cy + 0.5)``. Poses returned are COLMAP's cam_from_world, as in
``poses.csv``; points are in the same world.

Metric scale (:func:`metric_normalization`): SfM is up to a similarity. sellip puts the world
origin at the object centre (the coordinate-wise median of the sparse points), keeps SfM's
orientation, and scales the world so that the median distance from the registered camera
centres to that centre equals ``scene.distance_m`` of capture.yaml.
"""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from sellip.geometry.alignment import Similarity
from sellip.settings import setting

log = logging.getLogger(__name__)


class RegistrationError(RuntimeError):
    """Too few views registered. ``unregistered`` lists their view ids."""

    def __init__(self, message: str, unregistered: list[str]):
        super().__init__(message)
        self.unregistered = unregistered


POSE_MODES = ("known", "verify", "sfm")
"""Where the poses come from (config ``sfm.mode``; :func:`sellip.geometry.poses.solve_poses`)."""

MATCHING = ("auto", "exhaustive", "retrieval")
"""How SfM pairs the views (``SfmOptions.matching``)."""


@dataclass(frozen=True)
class SfmOptions:
    """Settings of the poses stage (config section ``sfm``; each setting declared once here, :mod:`sellip.settings`):
    :func:`sellip.geometry.poses.solve_poses` and :func:`run_sfm`.

    The other fields are the library's own: sequential_overlap: retrieval also matches the views this many before
    and after in capture order; octave_resolution: SIFT scales per octave (more finds more features);
    mask_dilation_px: the silhouette is grown by this many pixels before it restricts features; min_matches:
    matches needed for a verified pair; init_min_inliers: inliers of the initial pair (COLMAP's 100 suits megapixel
    images, not an object of 100 px); abs_pose_min_inliers: 2D-3D inliers to register a view; threads (-1: all
    cores) and seed: the job's (config ``seed``).
    """

    mode: str = setting("known", "use the capture's poses.csv (known; SfM runs only when there is none), run SfM "
                        "anyway and report its errors against poses.csv, which cameras.csv keeps (verify), or ignore "
                        "poses.csv (sfm). SfM poses are scaled so the median camera distance is scene.distance_m",
                        choices=POSE_MODES)
    matching: str = setting("auto", "view pairs matched: exhaustive, retrieval (bag-of-words neighbours + capture "
                            "order), or auto (exhaustive up to exhaustive_max_views views)", choices=MATCHING)
    exhaustive_max_views: int = setting(150, "auto matching is exhaustive up to this many views, retrieval above",
                                        minimum=2)
    retrieval_neighbors: int = setting(20, "retrieval: views matched with each view's most similar views", minimum=1)
    sequential_overlap: int = 3
    max_features: int = setting(8192, "SIFT features per image", minimum=100)
    feature_object_px: float = setting(400.0, "images are magnified (at most max_upscale times) until the object "
                                       "spans about this many pixels: SIFT finds few, coarse features on a small "
                                       "object", unit="pixels", exclusive_minimum=0)
    max_upscale: int = setting(3, "largest magnification of the images for features (1: never)", minimum=1)
    octave_resolution: int = 3
    refine_intrinsics: bool = setting(False, "let bundle adjustment refine the calibrated intrinsics (poorly "
                                      "constrained with a narrow field of view)")
    min_registered_fraction: float = setting(0.9, "stop with an error (naming the views) when fewer views register",
                                             unit="fraction of the views", minimum=0, maximum=1)
    mask_dilation_px: int = 4
    min_matches: int = 15
    init_min_inliers: int = 50
    abs_pose_min_inliers: int = 20
    threads: int = -1
    seed: int = 0


@dataclass
class SfmResult:
    """Registered cameras and sparse points of one reconstruction.

    view_ids: every input view, in input order; registered: (V,) bool; rotations (V, 3, 3) and
    translations (V, 3): cam_from_world, NaN for unregistered views. points (P, 3); colors (P, 3) uint8;
    errors (P,) mean reprojection error in pixels; tracks: per point, the indices of the views that
    observe it. reconstruction: the pycolmap.Reconstruction (same world as the arrays) or None.
    stats: counts and timings (seconds) for the report.
    """

    view_ids: list[str]
    registered: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    points: np.ndarray
    colors: np.ndarray
    errors: np.ndarray
    tracks: list[np.ndarray]
    reconstruction: object = None
    stats: dict = field(default_factory=dict)

    @property
    def unregistered_ids(self) -> list[str]:
        return [v for v, ok in zip(self.view_ids, self.registered) if not ok]


# --------------------------------------------------------------------------- images


def tone_map(image: np.ndarray, mask: np.ndarray | None = None, percentile: float = 99.5,
             gamma: float = 2.2) -> np.ndarray:
    """8-bit grey image (H, W) from a linear image (H, W) or (H, W, C) for feature extraction.

    Scaled so that the ``percentile`` of the object pixels (``mask``, default all non-zero pixels)
    maps to 255, then gamma-encoded (SIFT works on perceptual contrast); NaN becomes 0.
    """
    grey = np.nan_to_num(image.mean(axis=-1) if image.ndim == 3 else image, nan=0.0).astype(np.float32)
    region = grey[mask] if mask is not None and mask.any() else grey[grey > 0]
    level = np.percentile(region, percentile) if region.size else 1.0
    scaled = np.clip(grey / max(level, 1e-30), 0.0, 1.0) ** (1.0 / gamma)
    return np.rint(255 * scaled).astype(np.uint8)


def feature_upscale(masks: np.ndarray, object_px: float, max_upscale: int) -> int:
    """Integer image magnification so that the object spans about ``object_px`` pixels (1 to ``max_upscale``).

    SIFT finds few, coarse features on an object of a hundred pixels; magnifying the image first
    multiplies the features and the pose accuracy. masks (V, H, W) bool; the object size is the median
    over views of the longer side of the silhouette's bounding box.
    """
    sizes = []
    for mask in masks:
        rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        if rows.size:
            sizes.append(max(rows[-1] - rows[0], cols[-1] - cols[0]) + 1)
    if not sizes:
        return 1
    return int(np.clip(np.rint(object_px / np.median(sizes)), 1, max_upscale))


def feature_image(image: np.ndarray, mask: np.ndarray, upscale: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The 8-bit image (sH, sW) and mask (sH, sW) given to COLMAP for one view.

    image: (H, W[, C]) linear (I_d); mask: (H, W) bool. Magnified by ``upscale`` with cubic
    interpolation on the pixel-area grid (see :func:`scale_intrinsics` for the matching camera).
    """
    from scipy import ndimage

    grey = np.nan_to_num(image.mean(axis=-1) if image.ndim == 3 else image, nan=0.0).astype(np.float32)
    if upscale > 1:
        grey = ndimage.zoom(grey, upscale, order=3, grid_mode=True, mode="grid-constant")
        mask = ndimage.zoom(mask, upscale, order=0, grid_mode=True, mode="grid-constant")
    return tone_map(grey, mask), mask


def scale_intrinsics(intrinsics: np.ndarray, upscale: float) -> np.ndarray:
    """K (3, 3) of an image magnified by ``upscale`` on the pixel-area grid (pixel centres at integers):
    ``f' = s f``, ``c' = s (c + 0.5) - 0.5``."""
    k = np.array(intrinsics, np.float64)
    k[:2, :2] *= upscale
    k[:2, 2] = upscale * (k[:2, 2] + 0.5) - 0.5
    return k


def _image_name(index: int) -> str:
    return f"{index:05d}.png"


def _write_inputs(images: np.ndarray, masks: np.ndarray, work_dir: Path, dilation_px: int) -> tuple[Path, Path]:
    """Images and COLMAP masks (``<image name>.png``, zero = no features) under work_dir."""
    import imageio.v3 as iio
    from scipy import ndimage

    image_dir, mask_dir = work_dir / "images", work_dir / "masks"
    image_dir.mkdir(parents=True, exist_ok=True)
    mask_dir.mkdir(parents=True, exist_ok=True)
    for index, (image, mask) in enumerate(zip(images, masks)):
        if dilation_px:
            mask = ndimage.binary_dilation(mask, iterations=dilation_px)
        iio.imwrite(image_dir / _image_name(index), image)
        iio.imwrite(mask_dir / (_image_name(index) + ".png"), (mask * 255).astype(np.uint8))
    return image_dir, mask_dir


# --------------------------------------------------------------------------- matching


def match_pairs_by_retrieval(descriptors: list[np.ndarray], neighbours: int, overlap: int, words: int = 256,
                             seed: int = 0) -> np.ndarray:
    """Image pairs (M, 2), i < j, for large captures: retrieval plus capture-order neighbours.

    descriptors: per image an (N_i, 128) SIFT descriptor array. A vocabulary of ``words`` visual words
    (k-means on a sample of descriptors) gives each image a tf-idf histogram; each image is paired with
    its ``neighbours`` most similar images (cosine) and with the ``overlap`` images after it in order.
    """
    from scipy.cluster.vq import kmeans2, vq

    rng = np.random.default_rng(seed)
    count = len(descriptors)
    stacked = np.concatenate([d.astype(np.float32) for d in descriptors if len(d)])
    sample = stacked[rng.choice(len(stacked), size=min(len(stacked), 50 * words), replace=False)]
    codebook, _ = kmeans2(sample, min(words, len(sample)), minit="++", seed=seed)
    histograms = np.zeros((count, len(codebook)))
    for index, d in enumerate(descriptors):
        if len(d):
            np.add.at(histograms[index], vq(d.astype(np.float32), codebook)[0], 1.0)
    idf = np.log(count / np.maximum((histograms > 0).sum(axis=0), 1))
    weighted = histograms / np.maximum(histograms.sum(axis=1, keepdims=True), 1) * idf
    weighted /= np.maximum(np.linalg.norm(weighted, axis=1, keepdims=True), 1e-12)
    similarity = weighted @ weighted.T
    np.fill_diagonal(similarity, -np.inf)
    pairs = set()
    for i in range(count):
        for j in np.argsort(-similarity[i])[:neighbours]:
            pairs.add((min(i, int(j)), max(i, int(j))))
        for j in range(i + 1, min(i + 1 + overlap, count)):
            pairs.add((i, j))
    return np.array(sorted(pairs), np.int64).reshape(-1, 2)


def _match(database: Path, work_dir: Path, count: int, options: SfmOptions, device) -> str:
    """Run the matching strategy on the database; returns its name."""
    import pycolmap

    strategy = options.matching
    if strategy == "auto":
        strategy = "exhaustive" if count <= options.exhaustive_max_views else "retrieval"
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = options.threads
    verification = pycolmap.TwoViewGeometryOptions()
    verification.min_num_inliers = options.min_matches
    verification.ransac.random_seed = options.seed
    if strategy == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=matching, verification_options=verification,
                                  device=device)
        return strategy
    if strategy != "retrieval":
        raise ValueError(f"unknown sfm matching strategy {options.matching!r}; expected auto, exhaustive or retrieval")
    with pycolmap.Database.open(database) as db:
        images = sorted(db.read_all_images(), key=lambda image: image.name)
        descriptors = [np.asarray(db.read_descriptors(image.image_id).data) for image in images]
    pairs = match_pairs_by_retrieval(descriptors, options.retrieval_neighbors, options.sequential_overlap,
                                     seed=options.seed)
    pair_file = work_dir / "pairs.txt"
    pair_file.write_text("".join(f"{images[i].name} {images[j].name}\n" for i, j in pairs))
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = str(pair_file)
    pycolmap.match_image_pairs(database, matching_options=matching, pairing_options=pairing,
                               verification_options=verification, device=device)
    return f"retrieval ({len(pairs)} pairs)"


# --------------------------------------------------------------------------- mapping


def _mapping_options(options: SfmOptions):
    import pycolmap

    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = options.threads
    mapping.random_seed = options.seed
    mapping.min_num_matches = options.min_matches
    mapping.ba_refine_focal_length = options.refine_intrinsics
    mapping.ba_refine_principal_point = options.refine_intrinsics
    mapping.ba_refine_extra_params = False
    mapping.mapper.abs_pose_refine_focal_length = options.refine_intrinsics
    mapping.mapper.abs_pose_refine_extra_params = False
    mapping.mapper.init_min_num_inliers = options.init_min_inliers
    mapping.mapper.abs_pose_min_num_inliers = options.abs_pose_min_inliers
    mapping.mapper.random_seed = options.seed
    mapping.triangulation.random_seed = options.seed
    return mapping


def run_sfm(images: np.ndarray, masks: np.ndarray, intrinsics: np.ndarray, view_ids: list[str],
            work_dir: str | Path, options: SfmOptions = SfmOptions()) -> SfmResult:
    """Poses and sparse points from 8-bit images.

    images: (V, H, W) uint8 (see :func:`tone_map`); masks: (V, H, W) bool silhouettes (features only
    inside); intrinsics: (3, 3) OpenCV K shared by all views; work_dir: scratch folder (database,
    images), emptied first. Returns the largest reconstruction as an :class:`SfmResult`, in
    COLMAP's arbitrary similarity frame (see :func:`metric_normalization`).
    """
    import pycolmap

    work_dir = Path(work_dir)
    if work_dir.exists():
        shutil.rmtree(work_dir)
    work_dir.mkdir(parents=True)
    count, height, width = images.shape
    timings = {}
    start = time.perf_counter()
    image_dir, mask_dir = _write_inputs(images, masks, work_dir, options.mask_dilation_px)
    database = work_dir / "database.db"
    device = pycolmap.Device.cpu
    pycolmap.set_random_seed(options.seed)

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    k = np.asarray(intrinsics, np.float64)
    reader.camera_params = ",".join(repr(float(v)) for v in (k[0, 0], k[1, 1], k[0, 2] + 0.5, k[1, 2] + 0.5))
    reader.mask_path = str(mask_dir)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = options.threads
    extraction.sift.max_num_features = options.max_features
    extraction.sift.octave_resolution = options.octave_resolution
    names = [_image_name(i) for i in range(count)]
    pycolmap.extract_features(database, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction, device=device)
    timings["features_s"] = time.perf_counter() - start

    start = time.perf_counter()
    strategy = _match(database, work_dir, count, options, device)
    timings["matching_s"] = time.perf_counter() - start
    with pycolmap.Database.open(database) as db:
        keypoints = {image.name: db.num_keypoints_for_image(image.image_id) for image in db.read_all_images()}
        verified_pairs = db.num_verified_image_pairs()

    start = time.perf_counter()
    models = pycolmap.incremental_mapping(database, image_dir, work_dir / "sparse", options=_mapping_options(options))
    timings["mapping_s"] = time.perf_counter() - start
    reconstruction = max(models.values(), key=lambda r: r.num_reg_images()) if models else None
    result = result_from_reconstruction(reconstruction, view_ids, names)
    result.stats.update(
        timings=timings, matching=strategy, verified_pairs=int(verified_pairs), models=len(models),
        keypoints_per_view={v: int(keypoints.get(n, 0)) for v, n in zip(view_ids, names)},
        image_size=[int(width), int(height)],
    )
    log.info("SfM registered %d of %d views (%d points, %s matching, %.1f s)", result.registered.sum(), count,
             len(result.points), strategy, sum(timings.values()))
    return result


def result_from_reconstruction(reconstruction, view_ids: list[str], names: list[str]) -> SfmResult:
    """Arrays of an :class:`SfmResult` from a pycolmap reconstruction (None: nothing registered)."""
    count = len(view_ids)
    rotations = np.full((count, 3, 3), np.nan)
    translations = np.full((count, 3), np.nan)
    registered = np.zeros(count, bool)
    empty = SfmResult(list(view_ids), registered, rotations, translations, np.zeros((0, 3)),
                      np.zeros((0, 3), np.uint8), np.zeros(0), [], None)
    if reconstruction is None:
        return empty
    index_of_name = {name: i for i, name in enumerate(names)}
    index_of_image = {}
    for image_id, image in reconstruction.images.items():
        if not image.has_pose:
            continue
        i = index_of_name[image.name]
        pose = image.cam_from_world()
        rotations[i] = pose.rotation.matrix()
        translations[i] = pose.translation
        registered[i] = True
        index_of_image[image_id] = i
    points, colors, errors, tracks = [], [], [], []
    for point in reconstruction.points3D.values():
        points.append(point.xyz)
        colors.append(point.color)
        errors.append(point.error)
        tracks.append(np.unique([index_of_image[e.image_id] for e in point.track.elements]))
    return replace(empty, registered=registered, rotations=rotations, translations=translations,
                   points=np.asarray(points, np.float64).reshape(-1, 3),
                   colors=np.asarray(colors, np.uint8).reshape(-1, 3), errors=np.asarray(errors, np.float64),
                   tracks=tracks, reconstruction=reconstruction)


# --------------------------------------------------------------------------- frames and checks


def metric_normalization(result: SfmResult, distance_m: float) -> Similarity:
    """The similarity that puts the object centre at the origin and makes the median camera-to-centre
    distance ``distance_m`` (orientation unchanged). The object centre is the coordinate-wise median of
    the sparse points (of the optical axes' closest point when there are fewer than 10 points)."""
    from sellip.model.conventions import camera_center, camera_forward

    rotations, translations = result.rotations[result.registered], result.translations[result.registered]
    centers = camera_center(rotations, translations)
    if len(result.points) >= 10:
        target = np.median(result.points, axis=0)
    else:
        axes = camera_forward(rotations)
        projector = np.eye(3) - axes[:, :, None] * axes[:, None, :]
        target = np.linalg.solve(projector.sum(axis=0), np.einsum("vij,vj->i", projector, centers))
    scale = distance_m / float(np.median(np.linalg.norm(centers - target, axis=1)))
    return Similarity(scale, np.eye(3), -scale * target)


def transform_result(result: SfmResult, similarity: Similarity) -> SfmResult:
    """The result expressed in the world ``x' = s R x + t`` (poses, points and the pycolmap model)."""
    rotations, translations = similarity.apply_to_poses(result.rotations, result.translations)
    reconstruction = result.reconstruction
    if reconstruction is not None:
        import pycolmap

        reconstruction = pycolmap.Reconstruction(reconstruction)
        reconstruction.transform(pycolmap.Sim3d(similarity.scale, pycolmap.Rotation3d(similarity.rotation),
                                                similarity.translation))
    return replace(result, rotations=rotations, translations=translations, points=similarity.apply(result.points),
                   reconstruction=reconstruction)


def check_registration(result: SfmResult, min_fraction: float) -> None:
    """Raise :class:`RegistrationError` naming the unregistered views when fewer than ``min_fraction``
    of the views registered."""
    count = len(result.view_ids)
    registered = int(result.registered.sum())
    if registered >= max(min_fraction * count, 3):
        return
    missing = result.unregistered_ids
    shown = ", ".join(missing[:40]) + (f", ... ({len(missing) - 40} more)" if len(missing) > 40 else "")
    raise RegistrationError(
        f"SfM registered only {registered} of {count} views (need {min_fraction:.0%}); not registered: {shown}. "
        "Flash photographs need texture on the object and many overlapping views (70+ around 360 degrees, "
        "docs/design.md §4 notes). If the poses are known (a calibrated rig or turntable), supply them as poses.csv "
        "in the capture folder and run with sfm.mode: known.", missing)
