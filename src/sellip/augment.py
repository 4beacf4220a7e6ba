"""Specular augmentation (paper §4.3 "Specular and single scattering loss", Eqs. 24-25; DESIGN §5, §7).

A vertex rarely sees its own highlight in a sparse capture, so its lobe is under-determined.
Three pure steps (no I/O; the stage is :mod:`sellip.stages.cluster_lobes`):

1. :func:`cluster_materials`: K-means on the feature (eta, rho_d RGB) of the confidently fitted
   vertices, K chosen from the data by BIC (rule in :func:`choose_k`); clusters too small to fit
   are merged away; every vertex gets the label of its nearest centre.
2. :func:`fit_cluster_lobe`: per cluster, eta, sigma_s, sigma_ss, rho_s, rho_ss fitted to the
   pooled real observations of its vertices with a per-sample half-angle error Delta theta_h
   and the regularizer L_theta = lambda_theta Delta theta_h^2 (paper Eq. 25).
3. :func:`virtual_samples`: per vertex, M specular observations at theta_h = 0, step, ... rendered
   from its cluster's lobe, weighted by normalized cos theta_h; the fit adds them to its specular
   loss with weight ``FitSettings.lambda_g`` (:func:`sellip.fit.fit_vertices` ``virtual=``).

Features (:func:`cluster_features`): rho_d chromaticity (r, g of rho_d / sum rho_d) over 0.02,
log mean rho_d over 0.2, eta over 0.05: one unit is about a just-distinguishable material
difference in each, so the Euclidean K-means treats them alike.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from sellip import fit
from sellip.fit import FitSettings, Observations, VirtualSamples
from sellip.kernels import kernel

log = logging.getLogger(__name__)

CHROMA_SCALE = 0.02
LOG_BRIGHTNESS_SCALE = 0.2
ETA_SCALE = 0.05
VARIANCE_FLOOR = 0.5**2  # per-dimension variance floor of the BIC Gaussians (feature units): spreads below half a unit are not structure
REGION_OUTLIER_P = 1e-3  # an albedo in this tail of its cluster's robust Gaussian is an outlier (_region_centres)
REGION_EPS = 1.0  # outliers within this many albedo feature units of each other are one group (DBSCAN)
REGION_MIN_SAMPLES = 5  # ... with at least this many in a group's core
REGION_FIT_POINTS = 500  # the robust Gaussian is fitted to at most this many of a cluster's vertices (seeded): 0.03 s
CUT_ALBEDO_SD = 3.0  # two clusters whose mean albedos are closer than this many pooled sd may be one material ...
CUT_MODE_POINTS = 4000  # ... cut along its eta: their features along the line between the centres have one mode
CUT_ETA_SE = 3.0  # ... or, within CUT_MODES_ALBEDO_SD, two albedo modes whose etas split by albedo are this many SE apart
CUT_MODES_ALBEDO_SD = 5.0  # the albedo modes of one textured material: 2.4-4.1 sd apart; two real materials 5.45 and more


@dataclass(frozen=True)
class AugmentSettings:
    """Settings of the clustering and of the per-cluster lobe fit."""

    k_max: int = 8  # K is chosen in 1..k_max
    min_cluster_vertices: int = 50  # smaller clusters are merged into their nearest neighbour
    # A material occupies a region: a cluster whose vertices' nearest neighbours on the surface lie in it less
    # often than this (on average) is a split of a material's noise, not a material, and is merged; a region of
    # another albedo inside a cluster at least this coherent becomes a cluster (:func:`_region_centres`); and two
    # clusters that are one material cut along its eta are merged (:func:`_eta_cut`) (0: none of the three;
    # docs/augment.md).
    min_coherence: float = 0.5
    coherence_neighbours: int = 6  # the nearest vertices (3-D) that stand for a vertex's 1-ring
    min_confidence: float = 0.1  # vertices clustered and pooled: status fitted and confidence >= this
    cluster_points: int = 20000  # at most this many vertices (seeded subsample) choose K and the centres
    restarts: int = 4  # K-means++ restarts per K (the lowest inertia wins)
    max_samples: int = 16384  # (vertex, view) samples per cluster lobe fit (seeded subsample)
    lambda_theta: float = 1.0  # weight of L_theta = Delta theta_h^2 (radians): 1 deg costs a 1.7 % I_s error
    max_theta_error_deg: float = 5.0  # |Delta theta_h| bound
    alternations: int = 4  # (lobe parameters, Delta theta_h) alternations


class Clustering(NamedTuple):
    """labels (N,) int32 in 0..K-1 for every vertex; centres (K, 4) feature units; bic {K: value};
    merges: one dict per merged cluster (vertices, into, reason); used (N,) bool, the vertices clustered;
    regions: one dict per cluster added for a region of another albedo inside a cluster (:func:`_region_centres`);
    notes: what was degenerate (a rule that could not apply to these data, and what was done instead)."""

    labels: np.ndarray
    centres: np.ndarray
    bic: dict
    merges: list
    used: np.ndarray
    regions: tuple = ()
    notes: tuple = ()


class ClusterLobe(NamedTuple):
    """One cluster's lobe: eta, sigma_s, sigma_ss, rho_s (floats), rho_ss (3,), samples (count), loss;
    theta_h_deg (J,) and value (J,) the samples of the plot (paper Fig. 7b): half angle with its fitted
    Delta theta_h, and the mono lobe value per unit shading, comparable to :func:`lobe_curve`."""

    eta: float
    sigma_s: float
    sigma_ss: float
    rho_s: float
    rho_ss: np.ndarray
    samples: int
    loss: float
    theta_h_deg: np.ndarray
    value: np.ndarray


# --- clustering --------------------------------------------------------------------------------

def cluster_features(eta, rho_d) -> np.ndarray:
    """Feature (N, 4) of N vertices from eta (N,) and rho_d (N, 3): chromaticity (2), log brightness, eta."""
    rho_d = np.maximum(np.asarray(rho_d, np.float64), 1e-6)
    total = rho_d.sum(-1)
    chroma = rho_d[:, :2] / total[:, None]
    return np.column_stack([chroma / CHROMA_SCALE, np.log(total / 3) / LOG_BRIGHTNESS_SCALE,
                            np.asarray(eta, np.float64) / ETA_SCALE])


def _squared_distances(x, centres):
    return np.maximum(np.sum(x * x, 1)[:, None] - 2 * x @ centres.T + np.sum(centres * centres, 1)[None], 0)


def kmeans(x: np.ndarray, k: int, rng: np.random.Generator, restarts: int = 4, iterations: int = 100):
    """K-means++ seeding and Lloyd iterations, ``restarts`` times; the lowest inertia wins.

    x (n, d); returns (centres (k, d), labels (n,), inertia). Deterministic for a given ``rng`` state.
    """
    n = len(x)
    best = None
    for _ in range(restarts):
        centres = [x[rng.integers(n)]]
        d2 = _squared_distances(x, np.asarray(centres))[:, 0]
        for _ in range(1, k):
            total = d2.sum()
            index = rng.choice(n, p=d2 / total) if total > 0 else rng.integers(n)
            centres.append(x[index])
            d2 = np.minimum(d2, _squared_distances(x, x[index][None])[:, 0])
        centres = np.asarray(centres)
        for _ in range(iterations):
            labels = np.argmin(_squared_distances(x, centres), 1)
            counts = np.bincount(labels, minlength=k)
            sums = np.zeros_like(centres)
            np.add.at(sums, labels, x)
            new = np.where(counts[:, None] > 0, sums / np.maximum(counts, 1)[:, None], centres)
            if np.allclose(new, centres, rtol=0, atol=1e-10):
                break
            centres = new
        d2 = _squared_distances(x, centres)
        labels = np.argmin(d2, 1)
        inertia = float(np.take_along_axis(d2, labels[:, None], 1).sum())
        if best is None or inertia < best[2]:
            best = (centres, labels, inertia)
    return best


def bic(x: np.ndarray, labels: np.ndarray, k: int) -> float:
    """Bayesian information criterion of a partition of x (n, d) into k clusters (lower is better).

    Each cluster is a Gaussian with its own diagonal covariance (variances floored at
    :data:`VARIANCE_FLOOR`) and a mixing weight: 2 d k + k - 1 parameters.
    """
    n, d = x.shape
    log_likelihood = 0.0
    for j in range(k):
        members = x[labels == j]
        if len(members) == 0:
            continue
        variance = np.maximum(members.var(0), VARIANCE_FLOOR)
        log_likelihood += (len(members) * np.log(len(members) / n)
                           - 0.5 * len(members) * np.sum(np.log(2 * np.pi * variance)) - 0.5 * len(members) * d)
    return float(-2 * log_likelihood + (2 * d * k + k - 1) * np.log(n))


def choose_k(x: np.ndarray, k_max: int, rng: np.random.Generator, restarts: int = 4):
    """K-means for K = 1..k_max (at most one cluster per 2 points); K with the lowest BIC.

    Returns (K, centres (K, d), bic {K: value}).
    """
    results, values = {}, {}
    for k in range(1, max(1, min(k_max, len(x) // 2)) + 1):
        centres, labels, _ = kmeans(x, k, rng, restarts)
        results[k] = centres
        values[k] = bic(x, labels, k)
    k = min(values, key=values.get)
    return k, results[k], values


def spatial_coherence(labels, vertices, neighbours: int = 6) -> np.ndarray:
    """(K,) per cluster of ``labels`` (N,) in 0..K-1: the share of its vertices' ``neighbours`` nearest other
    vertices (``vertices`` (N, 3), a stand-in for the mesh's 1-ring) that are in the cluster too, averaged over
    its vertices (NaN for an empty cluster). A material's region scores near 1 (the demo's: 0.92-0.99; sphere_ior's
    seven: 0.92-0.97); a cluster that k-means cut out of one material's eta noise scores near its share of the
    surface (0.34-0.38 on the demo)."""
    return _coherence(np.asarray(labels, np.intp), nearest_vertices(vertices, neighbours))


def nearest_vertices(vertices, neighbours: int) -> np.ndarray:
    """(N, <= neighbours) the indices of each vertex's nearest other vertices."""
    from scipy.spatial import cKDTree

    vertices = np.asarray(vertices, np.float64)
    k = min(neighbours + 1, len(vertices))
    if k < 2:
        return np.zeros((len(vertices), 0), np.intp)
    return cKDTree(vertices).query(vertices, k=k)[1][:, 1:]


def _coherence(labels, near) -> np.ndarray:
    count = int(labels.max()) + 1 if labels.size else 0
    if near.shape[1] == 0:
        return np.ones(count)
    same = (labels[near] == labels[:, None]).mean(1)
    sums, members = np.bincount(labels, weights=same, minlength=count), np.bincount(labels, minlength=count)
    with np.errstate(invalid="ignore", divide="ignore"):
        return sums / members


def _region_centres(features, used, centres, near, settings: AugmentSettings, rng) -> tuple[np.ndarray, list, list]:
    """Centres (K + R, d) with a centre added for each small material that k-means left inside a cluster, one
    record per added centre, and the notes of clusters whose albedos had no spread (:func:`_robust_mahalanobis`).

    BIC does not spend a cluster on a material of 1 % of the surface (the demo's eyes and beak, 67 of 5.7k
    vertices, inside the plumage's cluster), and its median eta then is the plumage's. Per cluster: the albedo
    features (chromaticity, brightness; not the noisy eta) of its clustered vertices; a robust Gaussian
    (scikit-learn ``MinCovDet``, fitted to at most ``REGION_FIT_POINTS`` of them); the members in its
    ``REGION_OUTLIER_P`` tail; those grouped in albedo (DBSCAN, ``REGION_EPS`` feature units). A group is a
    material when it is a region: of its vertices' ``coherence_neighbours`` nearest vertices, those clustered
    are in the group at least ``min_coherence`` of the time (the demo's eyes: 0.56-0.66; the scattered tails of
    texture and noise on the demo, sphere_ior and the stability spheres: at most 0.39), and its centre, added,
    takes at least ``min_cluster_vertices`` clustered vertices. Its centre is the group's mean feature (eta too).
    """
    from scipy.stats import chi2
    from sklearn.cluster import DBSCAN

    labels = np.argmin(_squared_distances(features, centres), 1)
    threshold = chi2.ppf(1 - REGION_OUTLIER_P, 3)
    regions, notes = [], []
    for cluster in range(len(centres)):
        members = np.flatnonzero(used & (labels == cluster))
        if members.size < settings.min_cluster_vertices:
            continue
        albedo = features[members, :3]
        sample = albedo if len(albedo) <= REGION_FIT_POINTS else albedo[rng.choice(len(albedo), REGION_FIT_POINTS,
                                                                                    replace=False)]
        distances, note = _robust_mahalanobis(sample, albedo, rng, cluster)
        notes += [note] if note else []
        outliers = members[distances > threshold]
        if outliers.size < REGION_MIN_SAMPLES:
            continue
        groups = DBSCAN(eps=REGION_EPS, min_samples=REGION_MIN_SAMPLES).fit_predict(features[outliers, :3])
        for group in range(groups.max() + 1):
            region = np.zeros(len(features), bool)
            region[outliers[groups == group]] = True
            around = near[region]
            known = used[around]  # a neighbour without a clustered fit says nothing either way
            coherence = float(region[around][known].mean()) if known.any() else 0.0
            record = {"inside": cluster, "vertices": int(region.sum()), "coherence": round(coherence, 3)}
            if coherence < settings.min_coherence:
                log.debug("albedo outliers of cluster %d not a region: %s", cluster, record)
                continue
            trial = np.vstack([centres, features[region].mean(0)])
            record["clustered_vertices"] = int(np.sum(np.argmin(_squared_distances(features[used], trial), 1)
                                                      == len(centres)))
            if record["clustered_vertices"] < settings.min_cluster_vertices:
                log.debug("region inside cluster %d too small for a cluster: %s", cluster, record)
                continue
            log.info("cluster %d holds a region of another albedo (%d vertices, coherence %.2f): a cluster of its own",
                     cluster, region.sum(), coherence)
            centres = trial
            regions.append(record)
    return centres, regions, notes


DEGENERATE_VARIANCE = 1e-12  # a robust covariance eigenvalue below this (feature units^2) is no spread at all


def _robust_mahalanobis(sample: np.ndarray, x: np.ndarray, rng, cluster: int = -1) -> tuple[np.ndarray, str | None]:
    """Squared Mahalanobis distances (n,) of ``x`` (n, d) from the robust Gaussian (scikit-learn ``MinCovDet``) of
    ``sample`` (m, d), and a note when that Gaussian was degenerate (None otherwise).

    Where more than half of the sample shares one value in some direction (a texture of flat colours, dark vertices
    whose albedo sits at the feature floor: many identical rows), the minimum-covariance-determinant estimate is
    singular and ``MinCovDet`` raises. The robust Gaussian is then degenerate, not absent: its location is the
    sample's median and its spread in each direction without spread is ``VARIANCE_FLOOR`` (spreads below half a
    feature unit are not structure, as in :func:`bic`), so what differs from the shared value by more than about a
    unit is still an outlier. Logged; a non-degenerate sample gives ``MinCovDet``'s own distances.
    """
    from sklearn.covariance import MinCovDet

    import warnings

    try:
        with warnings.catch_warnings():  # "not full rank": handled below
            warnings.simplefilter("ignore", UserWarning)
            gaussian = MinCovDet(random_state=int(rng.integers(2**31))).fit(sample)
        location, covariance = gaussian.location_, gaussian.covariance_
    except ValueError:  # the support's covariance is 0: every direction is degenerate
        gaussian, location, covariance = None, np.median(sample, 0), np.zeros((sample.shape[1],) * 2)
    values, vectors = np.linalg.eigh(covariance)
    degenerate = ~(values > DEGENERATE_VARIANCE)
    if gaussian is not None and not degenerate.any():
        return gaussian.mahalanobis(x), None
    note = (f"cluster {cluster}: its albedos have no spread in {int(degenerate.sum())} of {len(values)} directions "
            f"(flat colours or dark vertices): the region search took a spread of {np.sqrt(VARIANCE_FLOOR):g} "
            "feature units there")
    log.info("%s", note)
    values = np.where(degenerate, VARIANCE_FLOOR, values)
    projected = (np.asarray(x, np.float64) - location) @ vectors
    return np.sum(projected**2 / values, 1), note


def _separation(gap: np.ndarray, pooled: np.ndarray) -> float:
    """Mahalanobis length of ``gap`` (d,) under the covariance ``pooled`` (d, d); a direction without spread (two
    flat colours) counts with ``VARIANCE_FLOOR``, as in :func:`_robust_mahalanobis`, so that a gap along it is
    large, not ignored."""
    values, vectors = np.linalg.eigh(pooled)
    degenerate = ~(values > DEGENERATE_VARIANCE)
    if not degenerate.any():
        return float(np.sqrt(gap @ np.linalg.lstsq(pooled, gap, rcond=None)[0]))
    projected = gap @ vectors
    return float(np.sqrt(np.sum(projected**2 / np.where(degenerate, VARIANCE_FLOOR, values))))


def _one_mode(x: np.ndarray, rng) -> bool:
    """Whether the 1-D sample ``x`` (n,) has one mode: a two-component Gaussian mixture fitted to it (at most
    CUT_MODE_POINTS, seeded) has one local maximum between its 0.5th and 99.5th percentiles."""
    from sklearn.mixture import GaussianMixture

    if len(x) > CUT_MODE_POINTS:
        x = rng.choice(x, CUT_MODE_POINTS, replace=False)
    if not np.ptp(x) > 0:  # one value (or NaN): one mode, and no mixture to fit
        return True
    mixture = GaussianMixture(2, random_state=int(rng.integers(2**31))).fit(x[:, None])
    grid = np.linspace(*np.percentile(x, [0.5, 99.5]), 400)[:, None]
    density = mixture.score_samples(grid)
    return int(np.sum((density[1:-1] > density[:-2]) & (density[1:-1] > density[2:]))) <= 1


def _same_eta_by_albedo(A: np.ndarray, B: np.ndarray, rng) -> bool:
    """Whether the features (n, 4) of two clusters are two albedo modes of one eta: their albedos (chromaticity,
    brightness) projected on the line between the two mean albedos have two modes, and their members split again by
    albedo alone (the nearer of the two mean albedos) have median etas within CUT_ETA_SE standard errors (each
    1.2533 x its robust sd / sqrt(n)). Two materials of one albedo are one albedo mode, whatever their etas.
    k-means on (albedo, eta) takes a material's high-eta vertices for one albedo mode and its low-eta ones for the
    other: tiny_speckle's rough material, two albedo modes 2.4 pooled sd apart, as two clusters at eta 1.384 and
    1.442 (true 1.40); split by albedo alone they are 1.397 and 1.411 (docs/accuracy.md)."""
    x = np.concatenate([A, B])
    line = B[:, :3].mean(0) - A[:, :3].mean(0)
    if not np.linalg.norm(line) > 0:  # one mean albedo: one albedo mode
        return False
    if _one_mode(x[:, :3] @ (line / np.linalg.norm(line)), rng):
        return False
    to_a = np.sum((x[:, :3] - A[:, :3].mean(0)) ** 2, 1) <= np.sum((x[:, :3] - B[:, :3].mean(0)) ** 2, 1)
    groups = [x[to_a, 3], x[~to_a, 3]]
    if min(len(g) for g in groups) < 5:
        return False
    medians = [np.median(g) for g in groups]
    se = [1.2533 * 1.4826 * np.median(np.abs(g - m)) / np.sqrt(len(g)) for g, m in zip(groups, medians)]
    return abs(medians[0] - medians[1]) <= CUT_ETA_SE * np.hypot(*se)


def _eta_cut(features, used, centres, rng) -> tuple[int, int, float] | None:
    """(keep, drop, separation) for the pair of clusters that is most likely one material cut along its eta noise,
    None when no pair is. A pair is when its mean albedos (chromaticity, brightness) are within CUT_ALBEDO_SD pooled
    standard deviations and its clustered vertices' features, projected on the line between the two centres, have
    one mode; or when they are within CUT_MODES_ALBEDO_SD and are two albedo modes of one eta
    (:func:`_same_eta_by_albedo`: a textured material, two modes on that line too). k-means cuts a material so when
    BIC takes more clusters than materials: sphere_ior's eta 1.462 wedge at 98k vertices, two halves at eta 1.507 and
    1.422, 1.97 sd apart in albedo, coherence 0.69 and 0.73, which the coherence test passes; the albedo modes of
    the stability spheres' materials 2.4-4.1 sd apart; two real materials are 5.4 sd apart and more on sphere_ior,
    the demo and the stability spheres (docs/accuracy.md). The larger cluster keeps its index."""
    labels = np.argmin(_squared_distances(features[used], centres), 1)
    x = features[used]
    members = [x[labels == k] for k in range(len(centres))]
    best = None
    for a in range(len(centres)):
        for b in range(a + 1, len(centres)):
            A, B = members[a], members[b]
            if len(A) < 5 or len(B) < 5:
                continue
            pooled = (np.cov(A[:, :3].T) * (len(A) - 1) + np.cov(B[:, :3].T) * (len(B) - 1)) / (len(A) + len(B) - 2)
            gap = A[:, :3].mean(0) - B[:, :3].mean(0)
            separation = _separation(gap, pooled)
            if separation >= CUT_MODES_ALBEDO_SD or (best is not None and separation >= best[2]):
                continue
            line = B.mean(0) - A.mean(0)
            line = line / np.linalg.norm(line) if np.linalg.norm(line) > 0 else line  # one centre: one mode
            if (separation < CUT_ALBEDO_SD and _one_mode(np.concatenate([A, B]) @ line, rng)) \
                    or _same_eta_by_albedo(A, B, rng):
                best = (a, b, separation) if len(A) >= len(B) else (b, a, separation)
    return best


def cluster_materials(eta, rho_d, status, confidence, settings: AugmentSettings = AugmentSettings(),
                      seed: int = 0, vertices=None) -> Clustering:
    """Material clusters of N vertices from their fitted eta (N,), rho_d (N, 3), status (N,) and confidence (N,).

    The vertices with status fitted and confidence >= ``min_confidence`` (a seeded subsample of at
    most ``cluster_points``) choose K (:func:`choose_k`) and the centres. A cluster with fewer than
    ``min_cluster_vertices`` of them is merged into the nearest other centre (logged), smallest first.
    With ``vertices`` (N, 3), a cluster whose spatial coherence (:func:`spatial_coherence`) is below
    ``min_coherence`` is then merged into the cluster most of its vertices' neighbours belong to, the least
    coherent first (logged): k-means on (chroma, brightness, eta) also cuts one material along its eta noise,
    and such a cut's median eta is biased by construction (the demo's plumage: a cluster of 396 of its vertices
    at eta 1.325 against 1.492, coherence 0.34). Before that test, a region of another albedo inside a cluster
    becomes a cluster of its own (:func:`_region_centres`), which that test then leaves (it passed it as a group).
    Last, two clusters that are one material cut along its eta (:func:`_eta_cut`) are merged, closest first. Every
    vertex, also unfitted ones, is labelled with its nearest centre; labels are ordered by cluster size (0 the
    largest).
    """
    rng = np.random.default_rng(seed)
    features = cluster_features(eta, rho_d)
    used = (np.asarray(status) == fit.STATUS_FITTED) & (np.asarray(confidence) >= settings.min_confidence)
    used &= ~fit.eta_at_bound(eta)  # no eta to cluster on: dark_noisy's vertices at 1.05 were a cluster of their own
    used &= np.all(np.isfinite(features), 1)
    if not used.any():  # nothing to cluster on: one cluster, said so (the stage fits its lobe on every vertex)
        note = (f"no vertex is fitted with confidence >= {settings.min_confidence} and an eta inside its range "
                f"({len(features)} vertices): one cluster of them all")
        log.warning("%s", note)
        finite = np.all(np.isfinite(features), 1)
        centre = np.median(features[finite], 0) if finite.any() else np.zeros(features.shape[1])
        return Clustering(labels=np.zeros(len(features), np.int32), centres=centre[None], bic={}, merges=[],
                          used=used, notes=(note,))
    pool = np.flatnonzero(used)
    if pool.size > settings.cluster_points:
        pool = np.sort(rng.choice(pool, settings.cluster_points, replace=False))
    _, centres, values = choose_k(features[pool], settings.k_max, rng, settings.restarts)
    merges = []
    while len(centres) > 1:
        labels = np.argmin(_squared_distances(features[pool], centres), 1)
        counts = np.bincount(labels, minlength=len(centres))
        small = int(np.argmin(counts))
        if counts[small] >= settings.min_cluster_vertices:
            break
        others = np.delete(np.arange(len(centres)), small)
        into = int(others[np.argmin(_squared_distances(centres[small][None], centres[others])[0])])
        merges.append({"cluster": small, "vertices": int(counts[small]), "into": into,
                       "reason": f"{int(counts[small])} confident vertices < min_cluster_vertices "
                                 f"{settings.min_cluster_vertices}"})
        log.info("cluster %d (%d confident vertices) merged into cluster %d: fewer than %d", small,
                 counts[small], into, settings.min_cluster_vertices)
        members = (labels == small) | (labels == into)
        centres[into] = features[pool][members].mean(0)
        centres = centres[others]
    near = nearest_vertices(vertices, settings.coherence_neighbours) if vertices is not None and settings.min_coherence > 0 \
        else None
    regions, notes = [], []
    if near is not None:
        centres, regions, notes = _region_centres(features, used, centres, near, settings, rng)
    # A region passed the coherence test as a group. As a cluster its centre also takes vertices of a similar albedo
    # elsewhere and its coherence can fall (the demo's eyes with 24 views: the group 0.65, its cluster 0.43): the
    # test below skips regions.
    is_region = np.arange(len(centres)) >= len(centres) - len(regions)
    while near is not None and len(centres) > 1:
        labels = np.argmin(_squared_distances(features, centres), 1)
        coherence = _coherence(labels, near)
        coherence = np.where(np.isnan(coherence) | is_region, np.inf, coherence)  # an empty cluster: no region
        worst = int(np.argmin(coherence))
        if coherence[worst] >= settings.min_coherence:
            break
        members = np.flatnonzero(labels == worst)
        around = labels[near[members]].ravel()
        others = np.delete(np.arange(len(centres)), worst)
        into = int(others[np.argmax(np.bincount(around, minlength=len(centres))[others])])
        merges.append({"cluster": worst, "vertices": int(members.size), "into": into,
                       "reason": f"spatially incoherent: {coherence[worst]:.2f} of its vertices' neighbours in it "
                                 f"< min_coherence {settings.min_coherence}"})
        log.info("cluster %d (%d vertices) merged into cluster %d: spatially incoherent (%.2f of its vertices' "
                 "neighbours in it)", worst, members.size, into, coherence[worst])
        merged = used & ((labels == worst) | (labels == into))
        if merged.any():
            centres[into] = features[merged].mean(0)
        centres, is_region = centres[others], is_region[others]
    while near is not None and len(centres) > 1:
        cut = _eta_cut(features, used, centres, rng)
        if cut is None:
            break
        keep, drop, separation = cut
        labels = np.argmin(_squared_distances(features, centres), 1)
        merges.append({"cluster": drop, "vertices": int(np.sum(used & (labels == drop))), "into": keep,
                       "reason": f"one material cut along its eta: mean albedos {separation:.2f} pooled sd apart, "
                                 f"one mode between the centres (< {CUT_ALBEDO_SD:g} sd) or two albedo modes of "
                                 f"one eta (< {CUT_MODES_ALBEDO_SD:g} sd)"})
        log.info("cluster %d merged into cluster %d: %s", drop, keep, merges[-1]["reason"])
        centres[keep] = features[used & ((labels == keep) | (labels == drop))].mean(0)
        centres = np.delete(centres, drop, axis=0)
    counts = np.bincount(np.argmin(_squared_distances(features[pool], centres), 1), minlength=len(centres))
    order = np.argsort(-counts, kind="stable")
    centres = centres[order]
    labels = np.argmin(_squared_distances(features, centres), 1).astype(np.int32)
    return Clustering(labels=labels, centres=centres, bic=values, merges=merges, used=used, regions=tuple(regions),
                      notes=tuple(notes))


# --- per-cluster lobe ----------------------------------------------------------------------------

class _Samples(NamedTuple):
    """Pooled (vertex, view) samples of one cluster as a one-vertex fit record (J slots) plus what the
    cluster fit adds: normal (J, 3) and rho_d (J, 3) / scale of each sample's vertex."""

    record: fit._Vertex
    normal: jnp.ndarray
    rho_d: jnp.ndarray


def _solve_spec(terms, target_s, w, prior):
    """Closed-form (rho_s, rho_ss RGB) (4,) of the cluster fit: exact NNLS (:func:`sellip.fit._nnls_specular`).
    A lobe the model leaves out has a zero basis (:func:`sellip.fit._lobe_terms`): its albedo comes out 0,
    and rho_s alone is the clamped 1-D least squares. target_s (J, 3): I_s minus its diffuse part."""
    basis_s, basis_ss = terms["lobe_s"] * terms["r_is"], terms["lobe_ss"] * terms["r_is"]
    ridge = 1e-6 * jnp.maximum(jnp.sum(w * (basis_s**2 + basis_ss**2)), 1e-12)
    return fit._nnls_specular(basis_s, basis_ss, target_s, w, prior, ridge)


def _cluster_residuals(z, delta, spec, samples: _Samples, settings: FitSettings, lambda_theta):
    """Residual matrix (J, 5) of the cluster fit: DoP, specular RGB, Delta theta_h (paper Eq. 25).

    z (5,) as :func:`sellip.fit._decode` (the normal entries unused); delta (J,) radians; spec (4,)
    rho_s, rho_ss RGB, or None to solve them (closed form, variable projection). The lobes are
    those of the record's model (``lobe_mask``, ``sigma_ss_fixed``: :func:`_with_model`; a lobe left
    out contributes nothing). Returns (res, spec).
    """
    v = samples.record
    frame = fit._Frame(*(jnp.array([0.0, 0.0, 1.0], z.dtype),) * 3)
    _, eta, sigma_s, sigma_ss = fit._decode(z, frame, fit._fixed_sigma_ss(v, settings))
    terms = fit._model_terms(samples.normal, eta, sigma_s, sigma_ss, v, theta_h_offset=delta, lobes=settings.lobes)
    w = v.weight * terms["lit"]
    diffuse_s = samples.rho_d * terms["d_is"][:, None]
    if spec is None:
        spec = _solve_spec(terms, v.obs_s - diffuse_s, w, v.prior)
    reflect = terms["lobe_s"][:, None] * spec[0] + terms["lobe_ss"][:, None] * spec[None, 1:]
    i_d = (v.obs_d - reflect * terms["r_id"][:, None]) @ v.color
    i_alpha = (v.obs_a - reflect * terms["r_ia"][:, None]) @ v.color
    i_beta = (v.obs_s - reflect * terms["r_is"][:, None]) @ v.color
    dop_measured = fit.measured_dop(terms, i_d, i_alpha, i_beta)
    sqrt_w = jnp.sqrt(w)
    res_psi = jnp.sqrt(settings.lambda_psi) * sqrt_w * (terms["dop"] - dop_measured)
    res_s = jnp.sqrt(settings.lambda_s) * sqrt_w[:, None] * (diffuse_s + reflect * terms["r_is"][:, None] - v.obs_s)
    res_theta = jnp.sqrt(lambda_theta * v.weight) * delta
    return jnp.concatenate([res_psi[:, None], res_s, res_theta[:, None]], 1), spec


class _Pool(NamedTuple):
    """Pooled samples of a cluster (:func:`_pool_samples`): the samples (J slots), the count of real
    ones, the intensity scale they are divided by, and vertex (count,) the row of each real sample."""

    samples: _Samples
    count: int
    scale: float
    vertex: np.ndarray


def _pool_samples(obs: Observations, normals, rho_d, settings: FitSettings, max_samples: int,
                  rng: np.random.Generator) -> _Pool:
    """The usable views (:func:`sellip.fit.select_views`) of n vertices as J <= max_samples samples,
    padded with weight-0 slots to the power of two at or above ``max_samples``: every cluster has
    the same shape, so the lobe fit compiles once per run (and once per machine with the persistent
    compilation cache)."""
    dtype = np.float64 if jax.config.jax_enable_x64 else np.float32
    settings = _kernel_settings(settings)
    obs = Observations(*[np.asarray(x, dtype) if np.asarray(x).dtype.kind == "f" else np.asarray(x) for x in obs])
    normals = np.asarray(normals, dtype) / np.linalg.norm(normals, axis=-1, keepdims=True)
    # Rows padded to 2048 or a power of two (repeats, cut off after): one compiled view selection serves clusters
    # and pools of any size (each size was a trace and a compile or cache load, 24 per demo job).
    n = len(normals)
    rows = np.minimum(np.arange(fit._bucket(n, minimum=2048)), max(n - 1, 0))
    keep = np.asarray(fit._select(Observations(*[jnp.asarray(np.asarray(x)[rows]) for x in obs]),
                                  jnp.asarray(normals[rows]), settings))[:n]
    vertex, view = np.nonzero(keep)
    if vertex.size > max_samples:
        pick = np.sort(rng.choice(vertex.size, max_samples, replace=False))
        vertex, view = vertex[pick], view[pick]
    count = vertex.size
    size = fit._bucket(max_samples, minimum=256)
    index_v = np.resize(vertex, size) if count else np.zeros(size, int)
    index_k = np.resize(view, size) if count else np.zeros(size, int)
    take = lambda x: np.asarray(x)[index_v, index_k]  # noqa: E731
    diffuse = take(obs.diffuse)
    valid = np.arange(size) < count
    scale = float(np.median(diffuse[:count].mean(-1))) if count else 1.0
    color = diffuse[:count].sum(0)
    color = color / color.sum() if count and color.sum() > 0 else np.full(3, 1 / 3)
    record = fit._Vertex(
        obs_d=diffuse / scale, obs_a=take(obs.diffuse_pol) / scale, obs_s=take(obs.specular) / scale,
        to_light=take(obs.to_light), to_camera=take(obs.to_camera), light_distance=take(obs.light_distance),
        camera_up=take(obs.camera_up), light_axis=take(obs.light_axis),
        weight=np.where(valid, 1.0 / max(count, 1), 0.0).astype(dtype), color=color.astype(dtype),
        scale=np.asarray(scale, dtype), prior=np.zeros(4, dtype))
    record = record._replace(**{name: jnp.asarray(getattr(record, name), dtype) for name in record._fields
                                if getattr(record, name) is not None})
    samples = _Samples(record, jnp.asarray(normals[index_v]), jnp.asarray(np.asarray(rho_d, dtype)[index_v] / scale))
    return _Pool(samples, count, scale, vertex)


def _stacked_residuals(z, delta, samples, settings, lambda_theta):
    return _cluster_residuals(z, delta, None, samples, settings, lambda_theta)[0].ravel()


_stacked = kernel(_stacked_residuals, static_argnames=("settings",))
_stacked_jacobian = kernel(jax.jacfwd(_stacked_residuals), static_argnames=("settings",),
                           name="sellip.augment._stacked_jacobian")


def _delta_step(z, delta, samples, settings: FitSettings, lambda_theta, max_delta, steps: int = 3, spec=None):
    """Gauss-Newton on each sample's Delta theta_h with the lobe parameters (and albedos) held:
    every sample's rows depend on its own Delta only. Accepts a step per sample only where it
    lowers that sample's cost. ``spec`` (4,) holds the albedos at given values (None: solved at the
    incoming delta)."""
    if spec is None:
        _, spec = _cluster_residuals(z, delta, None, samples, settings, lambda_theta)

    def rows(d):
        return _cluster_residuals(z, d, spec, samples, settings, lambda_theta)[0]

    for _ in range(steps):
        res, slope = jax.jvp(rows, (delta,), (jnp.ones_like(delta),))
        cost = jnp.sum(res**2, 1)
        new = jnp.clip(delta - jnp.sum(res * slope, 1) / (jnp.sum(slope**2, 1) + 1e-30), -max_delta, max_delta)
        better = jnp.sum(rows(new) ** 2, 1) < cost
        delta = jnp.where(better, new, delta)
    return delta


_delta_step_jit = kernel(_delta_step, static_argnames=("settings", "steps"))


@kernel(static_argnames=("settings",))
def _pool_solution(z, delta, samples: _Samples, settings: FitSettings, lambda_theta):
    """At the solution z of a cluster fit: its loss, albedos (4,), eta, sigma_s, sigma_ss, and per sample
    the measured lobe value (J,) and its shading R+(theta_d)/R+(0) x S (J,) (their ratio is comparable to
    :func:`lobe_curve`, plotted against theta_h + delta). One compiled kernel, not op-by-op dispatch."""
    res, spec = _cluster_residuals(z, delta, None, samples, settings, lambda_theta)
    frame = fit._Frame(*(jnp.array([0.0, 0.0, 1.0], z.dtype),) * 3)
    _, eta, sigma_s, sigma_ss = fit._decode(z, frame, fit._fixed_sigma_ss(samples.record, settings))
    terms = fit._model_terms(samples.normal, eta, sigma_s, sigma_ss, samples.record, theta_h_offset=delta)
    measured = (samples.record.obs_s - samples.rho_d * terms["d_is"][:, None]) @ samples.record.color
    shading = terms["r_is"] / fit.fresnel(jnp.ones((), z.dtype), eta).r_plus
    return jnp.sum(res**2), spec, eta, sigma_s, sigma_ss, measured, shading


@kernel(static_argnames=("settings",))
def _sample_losses(z, delta, spec, samples: _Samples, settings: FitSettings, lambda_theta):
    """The cluster loss of each sample (J,) with the lobe (z, albedos ``spec``) and deltas held."""
    res, _ = _cluster_residuals(z, delta, spec, samples, settings, lambda_theta)
    return jnp.sum(res**2, 1)


def lobe_fit_settings(settings: FitSettings) -> FitSettings:
    """The fields of ``settings`` the cluster fit uses (loss weights, lobe set, view selection), the
    others at their defaults: the jitted lobe kernels take the settings as a static argument, so
    passes that differ only in, e.g., ``fit_normal`` or ``max_iterations`` share one compilation."""
    keep = ("lambda_psi", "lambda_s", "lobes", "sigma_ss_fixed", "dark_threshold", "chroma_threshold",
            "outlier_threshold", "shading_outlier_floor")
    return FitSettings(**{name: getattr(settings, name) for name in keep})


def _kernel_settings(settings: FitSettings) -> FitSettings:
    """The static settings of the cluster kernels: :func:`lobe_fit_settings` with every lobe. The model
    (``settings.lobes``, ``sigma_ss_fixed``) travels as data in the samples' record (:func:`_with_model`),
    so that every candidate model of model selection runs one compiled program (four programs of five
    kernels each were 68 s of the demo's cold cluster_lobes job of 94 s)."""
    return dataclasses.replace(lobe_fit_settings(settings), lobes="full", sigma_ss_fixed=None)


def _with_model(samples: _Samples, settings: FitSettings) -> _Samples:
    """``samples`` whose record carries the model of ``settings`` (:func:`sellip.fit.model_of`) as the
    per-vertex fit's kernels take it: lobe_mask (2,) and the fixed sigma_ss (NaN: free)."""
    dtype = samples.record.obs_d.dtype
    lobe_mask, fixed = fit.model_arrays(np.array([fit.model_of(settings)]), settings.sigma_ss_fixed or 0.0)
    return samples._replace(record=samples.record._replace(lobe_mask=jnp.asarray(lobe_mask[0], dtype),
                                                           sigma_ss_fixed=jnp.asarray(fixed[0], dtype)))


def _free_lobe_parameters(settings: FitSettings) -> list[int]:
    """Indices into z of the cluster fit's nonlinear parameters: eta (2), and sigma_s (3), sigma_ss (4)
    where the lobe set fits them (:func:`sellip.fit._free_parameters` without the normal)."""
    return list(fit._free_parameters(dataclasses.replace(settings, fit_normal=False)))


def fit_cluster_lobe(obs: Observations, normals, rho_d, eta0: float, fit_settings: FitSettings | None = None,
                     settings: AugmentSettings = AugmentSettings(), seed: int = 0) -> ClusterLobe:
    """Fit one cluster's lobe to the pooled observations of its n vertices (paper Eq. 25).

    obs: :class:`sellip.fit.Observations` (n, K); normals (n, 3) and rho_d (n, 3): the vertices'
    fitted normals and albedos (held). eta0: the start of eta (e.g. the members' median).
    Minimizes lambda_psi L_psi + lambda_s L_s' + lambda_theta sum_j w_j Delta theta_h_j^2 over eta,
    sigma_s, sigma_ss (LM, scipy ``least_squares`` on the fit's bounded parameterization), rho_s
    and rho_ss (closed form) and Delta theta_h (J,) (per-sample Gauss-Newton), alternating
    ``settings.alternations`` times. Intensities are divided by the cluster's median diffuse level.
    The lobes are those of ``fit_settings.lobes`` and ``sigma_ss_fixed`` (the model, :mod:`sellip.models`):
    a lobe left out has albedo 0 (its roughness is then the start value, unused).
    """
    fit_settings = lobe_fit_settings(fit_settings or FitSettings())
    pool = _pool_samples(obs, normals, rho_d, fit_settings, settings.max_samples, np.random.default_rng(seed))
    if pool.count == 0:
        raise ValueError("the cluster has no usable (vertex, view) sample")
    return _fit_pool(pool, eta0, fit_settings, settings)


def _fit_pool(pool: _Pool, eta0: float, fit_settings: FitSettings, settings: AugmentSettings) -> ClusterLobe:
    """:func:`fit_cluster_lobe` on pooled samples."""
    from scipy.optimize import least_squares

    fit_settings = lobe_fit_settings(fit_settings)
    samples, count, scale = _with_model(pool.samples, fit_settings), pool.count, pool.scale
    static = _kernel_settings(fit_settings)  # the compiled kernels' (one program for every model)
    dtype = samples.record.obs_d.dtype
    lambda_theta = jnp.asarray(settings.lambda_theta, dtype)
    max_delta = jnp.asarray(np.radians(settings.max_theta_error_deg), dtype)
    delta = jnp.zeros(samples.normal.shape[0], dtype)
    free = _free_lobe_parameters(fit_settings)
    # Start: eta0 with the fit's roughness grid, the lowest loss.
    grid = np.asarray(fit.ROUGHNESS_GRID)
    starts = np.asarray(fit._encode(jnp.full(len(grid), eta0, dtype), jnp.asarray(grid[:, 0], dtype),
                                    jnp.asarray(grid[:, 1], dtype), dtype))
    if fit_settings.lobes == "diffuse":  # no roughness to start from: one start
        starts = starts[:1]
    costs = [float(jnp.sum(_stacked(jnp.asarray(s), delta, samples, static, lambda_theta) ** 2)) for s in starts]
    z = starts[int(np.argmin(costs))].astype(np.float64)

    def solve(z, delta):
        def residual(x):
            full = z.copy()
            full[free] = x
            return np.asarray(_stacked(jnp.asarray(full, dtype), delta, samples, static, lambda_theta), np.float64)

        def jacobian(x):
            full = z.copy()
            full[free] = x
            jac = _stacked_jacobian(jnp.asarray(full, dtype), delta, samples, static, lambda_theta)
            return np.asarray(jac, np.float64)[:, free]

        result = least_squares(residual, z[free], jac=jacobian, method="lm", xtol=1e-8, ftol=1e-8, max_nfev=100)
        z = z.copy()
        z[free] = result.x
        return z

    # Without a lobe, Delta theta_h changes nothing: one solve.
    for _ in range(settings.alternations if fit_settings.lobes != "diffuse" else 0):
        z = solve(z, delta)
        delta = _delta_step_jit(jnp.asarray(z, dtype), delta, samples, static, lambda_theta, max_delta)
    z = solve(z, delta)
    loss, spec, eta, sigma_s, sigma_ss, measured, shading = _pool_solution(jnp.asarray(z, dtype), delta, samples,
                                                                          static, lambda_theta)
    eta, sigma_s, sigma_ss = float(eta), float(sigma_s), float(sigma_ss)
    measured, shading = np.asarray(measured), np.asarray(shading)
    ok = (shading > 1e-6) & (np.arange(shading.shape[0]) < count)
    theta_h = np.degrees(np.arccos(np.clip(np.sum(np.asarray(samples.normal) * _unit(
        np.asarray(samples.record.to_light) + np.asarray(samples.record.to_camera)), -1), -1, 1)))
    return ClusterLobe(eta=eta, sigma_s=sigma_s, sigma_ss=sigma_ss, rho_s=float(spec[0]) * scale,
                       rho_ss=np.asarray(spec[1:], np.float64) * scale, samples=int(count),
                       loss=float(loss),
                       theta_h_deg=(theta_h + np.degrees(np.asarray(delta)))[ok],
                       value=(measured / np.where(shading > 1e-6, shading, 1) * scale)[ok])


def no_lobe(eta: float) -> ClusterLobe:
    """The lobe of a cluster without a usable sample: no specular and no single scattering (albedos 0), ``eta``,
    the roughness starts of the fit; ``samples`` 0. Its model is diffuse only (code 0)."""
    return ClusterLobe(eta=float(eta), sigma_s=float(fit.ROUGHNESS_GRID[0][0]), sigma_ss=float(fit.ROUGHNESS_GRID[0][1]),
                       rho_s=0.0, rho_ss=np.zeros(3), samples=0, loss=0.0, theta_h_deg=np.zeros(0), value=np.zeros(0))


def lobe_sample_losses(lobe: ClusterLobe, pool: _Pool, fit_settings: FitSettings,
                       settings: AugmentSettings = AugmentSettings(), delta_rounds: int = 2) -> np.ndarray:
    """The cluster loss of each real sample of ``pool`` (count,) under a given lobe (held): the
    rows of :func:`_cluster_residuals` with the lobe's eta, roughnesses and albedos, and each
    sample's own Delta theta_h fitted (a per-sample nuisance, with its L_theta cost) by
    ``delta_rounds`` x 3 Gauss-Newton steps. Summed, it is the cluster fit's loss on these samples:
    the held-out error of model selection (:func:`sellip.models.select_model`)."""
    fit_settings = lobe_fit_settings(fit_settings)
    samples, static = _with_model(pool.samples, fit_settings), _kernel_settings(fit_settings)
    dtype = samples.record.obs_d.dtype
    lambda_theta = jnp.asarray(settings.lambda_theta, dtype)
    max_delta = jnp.asarray(np.radians(settings.max_theta_error_deg), dtype)
    z = fit._encode(jnp.asarray(lobe.eta, dtype), jnp.asarray(lobe.sigma_s, dtype),
                    jnp.asarray(max(lobe.sigma_ss, lobe.sigma_s + fit.LOBE_GAP), dtype), dtype)
    spec = jnp.asarray(np.concatenate([[lobe.rho_s], np.asarray(lobe.rho_ss)]) / pool.scale, dtype)
    delta = jnp.zeros(samples.normal.shape[0], dtype)
    for _ in range(delta_rounds if fit_settings.lobes != "diffuse" else 0):
        delta = _delta_step_jit(z, delta, samples, static, lambda_theta, max_delta, spec=spec)
    return np.asarray(_sample_losses(z, delta, spec, samples, static, lambda_theta), np.float64)[:pool.count]


def _unit(v):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def lobe_curve(theta_h_deg, lobe: ClusterLobe, color=(1 / 3, 1 / 3, 1 / 3)) -> np.ndarray:
    """The mono coaxial lobe value per unit shading (:func:`sellip.fit.virtual_reflectance` weighted by
    ``color``) at half angles theta_h_deg (M,) degrees. Returns (M,)."""
    values = fit.virtual_reflectance(jnp.radians(jnp.asarray(theta_h_deg, jnp.float64 if jax.config.jax_enable_x64
                                                             else jnp.float32)), *_lobe_arrays([lobe]))
    return np.asarray(values[0] @ jnp.asarray(color, values.dtype))


def _lobe_arrays(lobes):
    """(eta, rho_s, sigma_s, rho_ss, sigma_ss) arrays (K,), (K, 3) of cluster lobes."""
    dtype = np.float64 if jax.config.jax_enable_x64 else np.float32
    return (jnp.asarray([lb.eta for lb in lobes], dtype), jnp.asarray([lb.rho_s for lb in lobes], dtype),
            jnp.asarray([lb.sigma_s for lb in lobes], dtype), jnp.asarray(np.stack([lb.rho_ss for lb in lobes]), dtype),
            jnp.asarray([lb.sigma_ss for lb in lobes], dtype))


# --- virtual samples -----------------------------------------------------------------------------

def virtual_theta_h(settings: FitSettings | None = None) -> np.ndarray:
    """The M half angles (radians) of the virtual samples: 0, step, ..., (M - 1) step (paper: 0..89.5 deg)."""
    settings = settings or FitSettings()
    theta = np.radians(settings.virtual_step_deg) * np.arange(settings.virtual_count)
    if settings.virtual_count < 1 or theta[-1] >= np.pi / 2:
        raise ValueError(f"virtual samples need 1 <= virtual_count and (virtual_count - 1) * virtual_step_deg < 90, "
                         f"got {settings.virtual_count} x {settings.virtual_step_deg} deg")
    return theta


def virtual_samples(labels, lobes: list[ClusterLobe] | None, settings: FitSettings | None = None,
                    dtype=np.float32) -> VirtualSamples:
    """Virtual specular samples of N vertices from their cluster labels (N,) and the clusters' lobes.

    Every vertex gets the M samples of its cluster's lobe (:func:`sellip.fit.virtual_reflectance`)
    at :func:`virtual_theta_h`, weights w^a = cos theta_h / sum cos theta_h. A label < 0 (no
    cluster) gets weight 0. Returns :class:`sellip.fit.VirtualSamples` of numpy arrays (N, M, ...).
    """
    labels = np.asarray(labels)
    theta = virtual_theta_h(settings)
    if lobes:
        table = np.asarray(fit.virtual_reflectance(jnp.asarray(np.broadcast_to(theta, (len(lobes), theta.size))),
                                                   *_lobe_arrays(lobes)))  # (K, M, 3)
    else:
        table = np.zeros((0, theta.size, 3))
    if labels.size and labels.max(initial=-1) >= len(table):
        raise ValueError(f"cluster label {labels.max()} but only {len(table)} cluster lobes")
    weight = np.cos(theta) / np.cos(theta).sum()
    has = labels >= 0
    reflectance = np.zeros((labels.size, theta.size, 3))
    if len(table):
        reflectance[has] = table[labels[has]]
    return VirtualSamples(theta_h=np.broadcast_to(theta, (labels.size, theta.size)).astype(dtype),
                          reflectance=reflectance.astype(dtype),
                          weight=np.where(has[:, None], weight[None], 0.0).astype(dtype))


VALUE_SOURCES = {0: "material", 1: "vertex"}
"""Codes of ``eta_source`` and ``lobe_source`` in final/params.zarr and model.ply: the vertex carries its
material cluster's value, or its own (its data differ from the material's significantly)."""


def cluster_medians(value, labels, use, fallback) -> np.ndarray:
    """(K,) the median of ``value`` (N,) over each cluster's vertices (``labels`` (N,) in 0..K-1) where ``use`` (N,)
    bool; ``fallback`` (K,) for a cluster with no such vertex. A material's eta is the median of its vertices' own
    fits: on sphere_ior (24 views of 612x512, ten iterations) 0.59 / 0.88 % mean / worst per material against the
    cluster lobe fit's 0.75 / 2.33 %, on the demo's plumage and disc 0.63 / 1.01 % against 1.35 / 0.73 %."""
    value, labels, use = np.asarray(value, np.float64), np.asarray(labels, np.intp), np.asarray(use, bool)
    out = np.array(fallback, np.float64, copy=True)
    for k in np.unique(labels[use]):
        out[k] = np.median(value[use & (labels == k)])
    return out


def material_or_own(value, value_std, labels, cluster_value, deviation_sigmas: float = 3.0, std_floor: float = 0.01,
                    neighbours=None, min_support: int = 0):
    """A property of the material, not of the vertex (DESIGN §7: no more model than the scene needs): each
    vertex takes its cluster's value unless its own fitted value differs from it by more than
    ``deviation_sigmas`` of its own uncertainty, and, with ``neighbours``, at least ``min_support`` of its
    neighbours differ from theirs the same way, by as much: a deviation the data demand is a spot, not one vertex.

    value, value_std (N,): the vertices' fitted value (eta, sigma_s) and its Gauss-Newton std (inf where
    unknown: such a vertex always takes the material's); labels (N,) int cluster of each vertex;
    cluster_value (K,). ``std_floor`` keeps an overconfident fit (a few views, a tiny std) from splitting
    off on noise. ``neighbours`` (N, k) int: each vertex's nearest vertices (:func:`nearest_vertices`). Isolated
    deviations are the per-vertex fits' outliers: on the tiny stability sphere 63 of 2,384 vertices passed 3 std
    alone, every one 18-30 % off (a fit pinned at eta's lower bound by a depolarized sample, or a highlight between
    the views), and together cost 1.5 dB of held-out PSNR (docs/accuracy.md, "A deviation is a spot"). ``deviation_sigmas`` <= 0 keeps every
    vertex's own value. Returns (value (N,), source (N,) uint8 with :data:`VALUE_SOURCES` codes). The map is then
    piecewise constant where the object is, and keeps a real boundary or a deviating spot where the data demand it.
    """
    value = np.asarray(value, np.float64)
    if deviation_sigmas <= 0:
        return value.copy(), np.ones(len(value), np.uint8)
    cluster_value = np.asarray(cluster_value, np.float64)
    material = cluster_value[np.asarray(labels, np.intp)]
    scale = np.maximum(np.nan_to_num(np.asarray(value_std, np.float64), nan=np.inf, posinf=np.inf), std_floor)
    side = np.sign(value - material) * (np.isfinite(scale) & (np.abs(value - material) > deviation_sigmas * scale))
    if neighbours is not None and min_support > 0:
        neighbours = np.asarray(neighbours, np.intp)
        support = (side[neighbours] == side[:, None]).sum(axis=1) if neighbours.shape[1] else np.zeros(len(value))
        side = np.where(support >= min_support, side, 0)
    own = side != 0
    return np.where(own, value, material), own.astype(np.uint8)
