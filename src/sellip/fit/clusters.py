"""Material clusters (paper §4.3, docs/design.md §7; docs/augment.md): K-means on the feature (eta, rho_d
RGB) of the confidently fitted vertices, K chosen by BIC; small clusters merged; spatially incoherent clusters
(a cut through one material's noise) merged; regions of another albedo inside a cluster added; a material cut
along its eta merged. Pure numpy/scikit-learn, no I/O.

Features (:func:`cluster_features`): rho_d chromaticity (r, g of rho_d / sum rho_d) over 0.02, log mean rho_d
over 0.2, eta over 0.05: one unit is about a just-distinguishable material difference in each. Degenerate
statistics (flat colours, no confident vertex) degrade to fewer clusters and a note, never an exception.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from sellip.fit import parameterization, records
from sellip.settings import setting

log = logging.getLogger(__name__)


CHROMA_SCALE = 0.02
LOG_BRIGHTNESS_SCALE = 0.2
ETA_SCALE = 0.05
# per-dimension variance floor of the BIC Gaussians (feature units): spreads below half a unit are not structure
VARIANCE_FLOOR = 0.5**2
REGION_OUTLIER_P = 1e-3  # an albedo in this tail of its cluster's robust Gaussian is an outlier (_region_centres)
REGION_EPS = 1.0  # outliers within this many albedo feature units of each other are one group (DBSCAN)
REGION_MIN_SAMPLES = 5  # ... with at least this many in a group's core
REGION_CORE_NEIGHBOURS = 2  # a group's member counts when at least this many of its nearest vertices are in the group
REGION_CORE_SHARE = 0.25  # ... and the core must be at least this share of the clustered vertices its centre takes
REGION_FIT_POINTS = 500  # the robust Gaussian is fitted to at most this many of a cluster's vertices (seeded): 0.03 s
CUT_ALBEDO_SD = 3.0  # two clusters whose mean albedos are closer than this many pooled sd may be one material ...
CUT_MODE_POINTS = 4000  # ... cut along its eta: their features along the line between the centres have one mode
CUT_ETA_SE = 3.0  # ... or, within CUT_MODES_ALBEDO_SD, two albedo modes whose etas split by albedo are this many
                  # SE apart
CUT_MODES_ALBEDO_SD = 5.0  # the albedo modes of one textured material: 2.4-4.1 sd apart; two real materials 5.45
                           # and more
KEPT_SHARE = 0.5  # a region was found before when at least this share of its core had one earlier material's label


@dataclass(frozen=True)
class AugmentSettings:
    """Settings of the clustering and of the per-cluster lobe fit (config section ``augment``: its fields declared
    with :func:`sellip.settings.setting`, each once here; the others are the library's own)."""

    k_max: int = setting(8, "material clusters K are chosen from the data in 1..k_max (docs/augment.md)", minimum=1)
    min_cluster_vertices: int = setting(50, "clusters with fewer fitted vertices are merged into the nearest one",
                                        minimum=1)
    # A material occupies a region: a cluster whose vertices' nearest neighbours on the surface lie in it less
    # often than this (on average) is a split of a material's noise, not a material, and is merged; a region of
    # another albedo inside a cluster at least this coherent becomes a cluster (:func:`_region_centres`); and two
    # clusters that are one material cut along its eta are merged (:func:`find_eta_cut`) (0: none of the three;
    # docs/augment.md).
    min_coherence: float = setting(0.5, "merge a cluster whose vertices' nearest neighbours lie in it less often than "
                                   "this (k-means cutting one material along its eta noise), split off a region of "
                                   "another albedo at least this coherent, and merge two clusters that are one "
                                   "material cut along its eta; 0 turns all three off (docs/augment.md)",
                                   unit="share of neighbours", minimum=0, maximum=1)
    # Hysteresis across passes (docs/reproducibility.md): a material found at one pass is not dropped at the next on
    # weaker evidence than found it. A region whose core was mostly one material of the previous pass, other than
    # its host cluster's, passes the coherence test at min_coherence less this (the demo's eyes: 0.56-0.66 when
    # found, 0.48 at the final pass of one noise seed, where they were lost and their eta went 8.5 % off).
    keep_coherence_margin: float = setting(0.1, "hysteresis: a region of another albedo that was a material of its own "
                                           "at the previous pass is split off at min_coherence less this (0: no "
                                           "hysteresis; docs/reproducibility.md)", unit="share of neighbours",
                                           minimum=0, maximum=1)
    coherence_neighbours: int = 6  # the nearest vertices (3-D) that stand for a vertex's 1-ring
    min_confidence: float = 0.1  # vertices clustered and pooled: status fitted and confidence >= this
    cluster_points: int = 20000  # at most this many vertices (seeded subsample) choose K and the centres
    restarts: int = 4  # K-means++ restarts per K (the lowest inertia wins)
    max_samples: int = setting(16384, "real observations per cluster used to fit its lobe (a seeded subsample; a power "
                               "of two: every cluster's fit then has this one shape and compiles once)", minimum=100)
    lambda_theta: float = 1.0  # weight of L_theta = Delta theta_h^2 (radians): 1 deg costs a 1.7 % I_s error
    max_theta_error_deg: float = 5.0  # |Delta theta_h| bound
    alternations: int = 4  # (lobe parameters, Delta theta_h) alternations
    # Trimmed lobe fits (docs/augment.md, "Trimmed lobe fits"): the cluster lobe is refitted up to trim_rounds
    # times without the vertices it fits worst, those whose mean sample loss lies more than trim_z robust SDs
    # (1.4826 MAD) above the median vertex's (another material's vertices, clustered by their greyed albedo). The
    # refits stop when the lobe stops moving; none starts where more than trim_max_share of the pooled vertices
    # would go (the losses are then skewed by the lobe itself) or fewer than trim_min_vertices are pooled (a few
    # vertices may be all that see the highlight). 0 rounds, the default: on the stability suite trimming fixed
    # pplastic_set's lobe, but model selection's candidate fits are not trimmed and mitsuba_set gained a false lobe
    # (on a Mitsuba capture drawn before the generator's polarizer fix, d82e1ef).
    trim_rounds: int = 0
    trim_z: float = 3.5
    trim_max_share: float = 0.15
    trim_min_vertices: int = 100
    # Coherent pools (docs/augment.md, "Coherent pools"): a cluster's lobe fit and model selection pool only its
    # vertices whose coherence_neighbours nearest vertices lie in the cluster at least this often, unless fewer than
    # half of its vertices would be left (0: every vertex, the default until it has run on the whole suite). A vertex
    # on the border of two materials sees both; clustered by its blended albedo, it joins a cluster of neither.
    pool_min_coherence: float = setting(0.0, "coherent pools: a cluster's lobe fit and model selection read only its "
                                        "vertices whose nearest neighbours lie in it at least this often (where half "
                                        "of its vertices do); 0: every vertex (docs/augment.md, \"Coherent pools\")",
                                        unit="share of neighbours", minimum=0, maximum=1)
    # Support (docs/reproducibility.md): the clustering is repeated this many times, each on a seeded
    # sellip.fit.cluster_support.SUPPORT_KEEP share of the clustered vertices with another seed, and each cluster's
    # support is the share of those repeats that find it again whole (clusters.json ``support``, materials.csv
    # ``cluster_support``). 0: not measured. It changes no decision; it says which one the data do not settle.
    stability_resamples: int = 0

    def __post_init__(self):
        for name in ("min_coherence", "pool_min_coherence"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"augment {name} must be in [0, 1] (a share of neighbours), got {getattr(self, name)}")
        if not isinstance(self.stability_resamples, (int, np.integer)) or self.stability_resamples < 0:
            raise ValueError(f"augment stability_resamples must be an integer >= 0, got {self.stability_resamples}")


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


# --- clustering --------------------------------------------------------------------------------

def cluster_features(eta, rho_d) -> np.ndarray:
    """Feature (N, 4) of N vertices from eta (N,) and rho_d (N, 3): chromaticity (2), log brightness, eta."""
    rho_d = np.maximum(np.asarray(rho_d, np.float64), 1e-6)
    total = rho_d.sum(-1)
    chroma = rho_d[:, :2] / total[:, None]
    return np.column_stack([chroma / CHROMA_SCALE, np.log(total / 3) / LOG_BRIGHTNESS_SCALE,
                            np.asarray(eta, np.float64) / ETA_SCALE])


def squared_distances(x, centres):
    """(n, k) squared distances of x (n, d) to centres (k, d), elementwise in float64: no BLAS product, whose
    kernels (and so the last bits, and an argmin between near-equal centres) differ between CPUs and thread counts
    (docs/reproducibility.md)."""
    x, centres = np.asarray(x, np.float64), np.asarray(centres, np.float64)
    out = np.zeros((len(x), len(centres)))
    for j in range(x.shape[1]):  # one feature at a time: a fixed order of the sum, memory n x k
        out += (x[:, j, None] - centres[None, :, j]) ** 2
    return out


def kmeans(x: np.ndarray, k: int, rng: np.random.Generator, restarts: int = 4, iterations: int = 100):
    """K-means++ seeding and Lloyd iterations, ``restarts`` times; the lowest inertia wins.

    x (n, d); returns (centres (k, d), labels (n,), inertia). Deterministic for a given ``rng`` state.
    """
    n = len(x)
    best = None
    for _ in range(restarts):
        centres = [x[rng.integers(n)]]
        d2 = squared_distances(x, np.asarray(centres))[:, 0]
        for _ in range(1, k):
            total = d2.sum()
            index = rng.choice(n, p=d2 / total) if total > 0 else rng.integers(n)
            centres.append(x[index])
            d2 = np.minimum(d2, squared_distances(x, x[index][None])[:, 0])
        centres = np.asarray(centres)
        for _ in range(iterations):
            labels = np.argmin(squared_distances(x, centres), 1)
            counts = np.bincount(labels, minlength=k)
            sums = np.zeros_like(centres)
            np.add.at(sums, labels, x)
            new = np.where(counts[:, None] > 0, sums / np.maximum(counts, 1)[:, None], centres)
            if np.allclose(new, centres, rtol=0, atol=1e-10):
                break
            centres = new
        d2 = squared_distances(x, centres)
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


def vertex_coherence(labels, near) -> np.ndarray:
    """(N,) the share of each vertex's nearest vertices ``near`` (N, m) (:func:`nearest_vertices`) that carry its
    label of ``labels`` (N,); 1 where it has no neighbour."""
    labels, near = np.asarray(labels), np.asarray(near, np.intp)
    if near.shape[1] == 0:
        return np.ones(len(labels))
    return (labels[near] == labels[:, None]).mean(1)


def _coherence(labels, near) -> np.ndarray:
    """(K,) the mean of :func:`vertex_coherence` per cluster, from integer counts: the sum does not depend on the
    vertices' order (the coherence test compares it with a threshold; docs/reproducibility.md)."""
    count = int(labels.max()) + 1 if labels.size else 0
    m = near.shape[1]
    same = (labels[near] == labels[:, None]).sum(1) if m else np.ones(len(labels), np.int64)  # no neighbours: 1
    sums = np.bincount(labels, weights=same, minlength=count)  # integers below 2**53: exact in any order
    members = np.bincount(labels, minlength=count) * max(m, 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return sums / members


def _region_centres(features, used, centres, near, settings: AugmentSettings, rng,
                    previous: np.ndarray | None = None) -> tuple[np.ndarray, list, list]:
    """Centres (K + R, d) with a centre added for each small material that k-means left inside a cluster, one
    record per added centre, and the notes of clusters whose albedos had no spread (:func:`robust_mahalanobis`).

    BIC does not spend a cluster on a material of 1 % of the surface (the demo's eyes and beak, 67 of 5.7k
    vertices, inside the plumage's cluster), and its median eta then is the plumage's. Per cluster: the albedo
    features (chromaticity, brightness; not the noisy eta) of its clustered vertices; a robust Gaussian
    (scikit-learn ``MinCovDet``, fitted to at most ``REGION_FIT_POINTS`` of them); the members in its
    ``REGION_OUTLIER_P`` tail; those grouped in albedo (DBSCAN, ``REGION_EPS`` feature units). A group is a
    material when it is a region: of its vertices' ``coherence_neighbours`` nearest vertices, those clustered
    are in the group at least ``min_coherence`` of the time (the demo's eyes: 0.56-0.66; the scattered tails of
    texture and noise on the demo, sphere_ior and the stability spheres: at most 0.39), and its centre, added,
    takes at least :func:`region_size_floor` (``min_cluster_vertices``) clustered vertices. Its centre is the group's
    mean feature (eta too). Only the group's core counts: its members with at least ``REGION_CORE_NEIGHBOURS`` of
    their nearest vertices in the group (scattered tail vertices that DBSCAN chained to it are not the region), and
    it must be at least ``REGION_CORE_SHARE`` of the clustered vertices its centre takes.

    ``previous`` (N,) int: the previous pass's label of every vertex (None: the first pass). A group whose core is
    mostly (:data:`KEPT_SHARE`) one previous material other than the one most of its host cluster's vertices had
    was found before: it passes the coherence test at ``min_coherence - keep_coherence_margin`` (its record says
    ``found_before``), so that a material is not lost on less evidence than found it.
    """
    from scipy.stats import chi2
    from sklearn.cluster import DBSCAN

    labels = np.argmin(squared_distances(features, centres), 1)
    threshold = chi2.ppf(1 - REGION_OUTLIER_P, 3)
    regions, notes = [], []
    for cluster in range(len(centres)):
        members = np.flatnonzero(used & (labels == cluster))
        if members.size < settings.min_cluster_vertices:
            continue
        albedo = features[members, :3]
        sample = albedo if len(albedo) <= REGION_FIT_POINTS else albedo[rng.choice(len(albedo), REGION_FIT_POINTS,
                                                                                    replace=False)]
        distances, note = robust_mahalanobis(sample, albedo, rng, cluster)
        notes += [note] if note else []
        outliers = members[distances > threshold]
        if outliers.size < REGION_MIN_SAMPLES:
            continue
        host_before = _mode(previous[members]) if previous is not None else None
        groups = DBSCAN(eps=REGION_EPS, min_samples=REGION_MIN_SAMPLES).fit_predict(features[outliers, :3])
        for group in range(groups.max() + 1):
            region = np.zeros(len(features), bool)
            region[outliers[groups == group]] = True
            # Its core: the members with at least REGION_CORE_NEIGHBOURS of their nearest vertices in the group. DBSCAN
            # in albedo alone chains a small material's vertices with scattered tail vertices of a similar albedo
            # (none of whose neighbours are outliers), and whether it does turns on which vertices the robust
            # Gaussian put in its tail: the demo's eyes were one group of 41 (coherence 0.56) or lost in one of 128-167
            # (0.25-0.33) with another k-means seed or vertex order (issue #49, docs/reproducibility.md).
            inside = np.zeros(len(features), np.int64)
            inside[region] = region[near[region]].sum(1)
            region &= inside >= REGION_CORE_NEIGHBOURS
            if not region.any():
                continue
            around = near[region]
            known = used[around]  # a neighbour without a clustered fit says nothing either way
            coherence = float(region[around][known].mean()) if known.any() else 0.0
            record = {"inside": cluster, "vertices": int(region.sum()), "coherence": round(coherence, 3)}
            if coherence < _needed_coherence(region, previous, host_before, settings, record):
                log.debug("albedo outliers of cluster %d not a region: %s", cluster, record)
                continue
            trial = np.vstack([centres, features[region].mean(0)])
            record["clustered_vertices"] = int(np.sum(np.argmin(squared_distances(features[used], trial), 1)
                                                      == len(centres)))
            if record["clustered_vertices"] < region_size_floor(settings.min_cluster_vertices):
                log.debug("region inside cluster %d too small for a cluster: %s", cluster, record)
                continue
            if record["vertices"] < REGION_CORE_SHARE * record["clustered_vertices"]:
                # a few coherent vertices whose mean takes a hundred others is not their region's centre (pplastic_set's
                # first pass on a 90 % subsample: cores of 3-4 vertices, centres of 96-101; the demo's eyes: 0.44-0.9)
                log.debug("region inside cluster %d is not most of its centre's cluster: %s", cluster, record)
                continue
            log.info("cluster %d holds a region of another albedo (%d vertices, coherence %.2f): a cluster of its own",
                     cluster, region.sum(), coherence)
            centres = trial
            regions.append(record)
    return centres, regions, notes


def _needed_coherence(region, previous, host_before, settings: AugmentSettings, record: dict) -> float:
    """The coherence the group ``region`` (N,) bool needs: ``min_coherence``, or ``keep_coherence_margin`` less where
    most (:data:`KEPT_SHARE`) of it was one material of the ``previous`` pass other than its host cluster's
    (``host_before``); ``record["found_before"]`` then names it."""
    if previous is None:
        return settings.min_coherence
    before = _mode(previous[region])
    if before == host_before or np.mean(previous[region] == before) < KEPT_SHARE:
        return settings.min_coherence
    record["found_before"] = before
    return max(0.0, settings.min_coherence - settings.keep_coherence_margin)


def _mode(values: np.ndarray) -> int:
    """The most common of the non-negative ints ``values`` (the smallest on a tie)."""
    return int(np.argmax(np.bincount(np.asarray(values, np.int64))))


def region_size_floor(min_cluster_vertices: int) -> float:
    """The clustered vertices a region's centre must take: ``min_cluster_vertices`` less two Poisson standard errors
    of it (36 at 50). A region has passed the albedo and coherence tests a k-means cluster has not; its count is a
    draw (which confident vertices there are, which a centre takes): the demo's eyes took 43-53 of the 5.7k clustered
    vertices over resamples of one pass, and at the bare minimum they came and went with the draw (issue #49)."""
    return min_cluster_vertices - 2 * np.sqrt(min_cluster_vertices)


DEGENERATE_VARIANCE = 1e-12  # a robust covariance eigenvalue below this (feature units^2) is no spread at all


def robust_mahalanobis(sample: np.ndarray, x: np.ndarray, rng, cluster: int = -1) -> tuple[np.ndarray, str | None]:
    """Squared Mahalanobis distances (n,) of ``x`` (n, d) from the robust Gaussian (scikit-learn ``MinCovDet``) of
    ``sample`` (m, d), and a note when that Gaussian was degenerate (None otherwise).

    Where more than half of the sample shares one value in some direction (a texture of flat colours, dark vertices
    whose albedo sits at the feature floor: many identical rows), the minimum-covariance-determinant estimate is
    singular and ``MinCovDet`` raises. The robust Gaussian is then degenerate, not absent: its location is the
    sample's median and its spread in each direction without spread is ``VARIANCE_FLOOR`` (spreads below half a
    feature unit are not structure, as in :func:`bic`), so what differs from the shared value by more than about a
    unit is still an outlier. Logged; a non-degenerate sample gives ``MinCovDet``'s own distances.
    """
    import warnings

    from sklearn.covariance import MinCovDet

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


def albedo_separation(gap: np.ndarray, pooled: np.ndarray) -> float:
    """Mahalanobis length of ``gap`` (d,) under the covariance ``pooled`` (d, d); a direction without spread (two
    flat colours) counts with ``VARIANCE_FLOOR``, as in :func:`robust_mahalanobis`, so that a gap along it is
    large, not ignored."""
    values, vectors = np.linalg.eigh(pooled)
    degenerate = ~(values > DEGENERATE_VARIANCE)
    if not degenerate.any():
        return float(np.sqrt(gap @ np.linalg.lstsq(pooled, gap, rcond=None)[0]))
    projected = gap @ vectors
    return float(np.sqrt(np.sum(projected**2 / np.where(degenerate, VARIANCE_FLOOR, values))))


def one_mode(x: np.ndarray, rng) -> bool:
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


def same_eta_by_albedo(A: np.ndarray, B: np.ndarray, rng) -> bool:
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
    if one_mode(x[:, :3] @ (line / np.linalg.norm(line)), rng):
        return False
    to_a = np.sum((x[:, :3] - A[:, :3].mean(0)) ** 2, 1) <= np.sum((x[:, :3] - B[:, :3].mean(0)) ** 2, 1)
    groups = [x[to_a, 3], x[~to_a, 3]]
    if min(len(g) for g in groups) < 5:
        return False
    medians = [np.median(g) for g in groups]
    se = [1.2533 * 1.4826 * np.median(np.abs(g - m)) / np.sqrt(len(g)) for g, m in zip(groups, medians)]
    return abs(medians[0] - medians[1]) <= CUT_ETA_SE * np.hypot(*se)


def find_eta_cut(features, used, centres, rng) -> tuple[int, int, float] | None:
    """(keep, drop, separation) for the pair of clusters that is most likely one material cut along its eta noise,
    None when no pair is. A pair is when its mean albedos (chromaticity, brightness) are within CUT_ALBEDO_SD pooled
    standard deviations and its clustered vertices' features, projected on the line between the two centres, have
    one mode; or when they are within CUT_MODES_ALBEDO_SD and are two albedo modes of one eta
    (:func:`same_eta_by_albedo`: a textured material, two modes on that line too). k-means cuts a material so when
    BIC takes more clusters than materials: sphere_ior's eta 1.462 wedge at 98k vertices, two halves at eta 1.507 and
    1.422, 1.97 sd apart in albedo, coherence 0.69 and 0.73, which the coherence test passes; the albedo modes of
    the stability spheres' materials 2.4-4.1 sd apart; two real materials are 5.4 sd apart and more on sphere_ior,
    the demo and the stability spheres (docs/accuracy.md). The larger cluster keeps its index."""
    labels = np.argmin(squared_distances(features[used], centres), 1)
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
            separation = albedo_separation(gap, pooled)
            if separation >= CUT_MODES_ALBEDO_SD or (best is not None and separation >= best[2]):
                continue
            line = B.mean(0) - A.mean(0)
            line = line / np.linalg.norm(line) if np.linalg.norm(line) > 0 else line  # one centre: one mode
            if (separation < CUT_ALBEDO_SD and one_mode(np.concatenate([A, B]) @ line, rng)) \
                    or same_eta_by_albedo(A, B, rng):
                best = (a, b, separation) if len(A) >= len(B) else (b, a, separation)
    return best


def _merge_while(centres: np.ndarray, is_region: np.ndarray, find, merges: list) -> tuple[np.ndarray, np.ndarray]:
    """Merge clusters while ``find(centres, is_region)`` names one: it returns None, or (drop, into, vertices,
    reason, members): ``drop`` is merged into ``into`` (recorded in ``merges`` and logged), whose centre becomes the
    mean of ``members`` (the features of both clusters' vertices; kept when there are none). ``is_region`` (K,)
    flags follow the centres. Returns the centres and flags left."""
    while len(centres) > 1:
        found = find(centres, is_region)
        if found is None:
            break
        drop, into, vertices, reason, members = found
        merges.append({"cluster": drop, "vertices": vertices, "into": into, "reason": reason})
        log.info("cluster %d (%d vertices) merged into cluster %d: %s", drop, vertices, into, reason)
        centres = centres.copy()
        if len(members):
            centres[into] = members.mean(0)
        centres, is_region = np.delete(centres, drop, axis=0), np.delete(is_region, drop)
    return centres, is_region


def cluster_materials(eta, rho_d, status, confidence, settings: AugmentSettings = AugmentSettings(),
                      seed: int = 0, vertices=None, previous_labels=None) -> Clustering:
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
    Last, two clusters that are one material cut along its eta (:func:`find_eta_cut`) are merged, closest first. Every
    vertex, also unfitted ones, is labelled with its nearest centre; labels are ordered by cluster size (0 the
    largest). ``previous_labels`` (N,) int: the previous pass's clusters of the same vertices (None: none): a region
    that was a material there is kept on less coherence (hysteresis, ``keep_coherence_margin``).
    Long: the merge rules' finders are closures over the features and the pool; the driver is :func:`_merge_while`.
    """
    rng = np.random.default_rng(seed)
    features = cluster_features(eta, rho_d)
    previous = None
    if previous_labels is not None:
        previous = np.asarray(previous_labels, np.int64)
        if previous.shape != (len(features),) or (previous < 0).any():
            raise ValueError(f"previous_labels must be {len(features)} cluster labels >= 0 (one per vertex), got "
                             f"shape {previous.shape}")
    used = (np.asarray(status) == records.STATUS_FITTED) & (np.asarray(confidence) >= settings.min_confidence)
    # no eta to cluster on: dark_noisy's vertices at 1.05 were a cluster of their own
    used &= ~parameterization.eta_at_bound(eta)
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
    def too_small(centres, is_region):
        labels = np.argmin(squared_distances(features[pool], centres), 1)
        counts = np.bincount(labels, minlength=len(centres))
        small = int(np.argmin(counts))
        if counts[small] >= settings.min_cluster_vertices:
            return None
        others = np.delete(np.arange(len(centres)), small)
        into = int(others[np.argmin(squared_distances(centres[small][None], centres[others])[0])])
        return (small, into, int(counts[small]), f"{int(counts[small])} confident vertices < min_cluster_vertices "
                f"{settings.min_cluster_vertices}", features[pool][(labels == small) | (labels == into)])

    def incoherent(centres, is_region):
        labels = np.argmin(squared_distances(features, centres), 1)
        coherence = _coherence(labels, near)
        coherence = np.where(np.isnan(coherence) | is_region, np.inf, coherence)  # an empty cluster: no region
        worst = int(np.argmin(coherence))
        if coherence[worst] >= settings.min_coherence:
            return None
        members = np.flatnonzero(labels == worst)
        around = labels[near[members]].ravel()
        others = np.delete(np.arange(len(centres)), worst)
        into = int(others[np.argmax(np.bincount(around, minlength=len(centres))[others])])
        return (worst, into, int(members.size), f"spatially incoherent: {coherence[worst]:.2f} of its vertices' "
                f"neighbours in it < min_coherence {settings.min_coherence}",
                features[used & ((labels == worst) | (labels == into))])

    def eta_cut(centres, is_region):
        cut = find_eta_cut(features, used, centres, rng)
        if cut is None:
            return None
        keep, drop, separation = cut
        labels = np.argmin(squared_distances(features, centres), 1)
        return (drop, keep, int(np.sum(used & (labels == drop))),
                f"one material cut along its eta: mean albedos {separation:.2f} pooled sd apart, one mode between "
                f"the centres (< {CUT_ALBEDO_SD:g} sd) or two albedo modes of one eta (< {CUT_MODES_ALBEDO_SD:g} sd)",
                features[used & ((labels == keep) | (labels == drop))])

    merges = []
    centres, _ = _merge_while(centres, np.zeros(len(centres), bool), too_small, merges)
    coherent = vertices is not None and settings.min_coherence > 0
    near = nearest_vertices(vertices, settings.coherence_neighbours) if coherent else None
    regions, notes = [], []
    if near is not None:
        centres, regions, notes = _region_centres(features, used, centres, near, settings, rng, previous)
        # A region passed the coherence test as a group. As a cluster its centre also takes vertices of a similar
        # albedo elsewhere and its coherence can fall (the demo's eyes with 24 views: the group 0.65, its cluster
        # 0.43): the coherence test skips regions.
        is_region = np.arange(len(centres)) >= len(centres) - len(regions)
        merged = len(merges)
        centres, _ = _merge_while(centres, is_region, incoherent, merges)
        if len(merges) > merged:
            # The same question whichever path proposed the material: a small region of another albedo that k-means
            # found as a cluster of its own (BIC's K by a hair) was not a region, and as a cluster its centre also
            # takes scattered vertices of a similar albedo; the coherence test then merged it, where found by the
            # search above it is kept. So the search runs again on what the merges left (its own seeded stream:
            # the rules after it draw what they drew before). The demo's eyes: 54 vertices at coherence 0.44,
            # merged at 2 of 7 passes on another CPU (issue #49; docs/reproducibility.md).
            centres, again, more_notes = _region_centres(features, used, centres, near, settings,
                                                         np.random.default_rng([seed, 1]), previous)
            regions += [{**record, "after_merges": True} for record in again]
            notes += [note for note in more_notes if note not in notes]
        centres, _ = _merge_while(centres, np.zeros(len(centres), bool), eta_cut, merges)
    counts = np.bincount(np.argmin(squared_distances(features[pool], centres), 1), minlength=len(centres))
    order = np.argsort(-counts, kind="stable")
    centres = centres[order]
    labels = np.argmin(squared_distances(features, centres), 1).astype(np.int32)
    return Clustering(labels=labels, centres=centres, bic=values, merges=merges, used=used, regions=tuple(regions),
                      notes=tuple(notes))
