"""The cluster-lobes output directory (``labels.npy``, ``models.npy``, ``lobes.csv``, ``lobes.png``,
``clusters.json``): its schema, readers, the settings it records, and the lobe plot (paper Fig. 7b).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

LOBE_COLUMNS = ("cluster", "vertices", "eta", "sigma_s", "sigma_ss", "rho_s", "rho_ss_r", "rho_ss_g", "rho_ss_b",
                "samples", "loss", "model")



def lobes_schema():
    """pandera schema of lobes.csv."""
    import pandera.pandas as pa

    from sellip.model.params import MODEL_NAMES

    finite = pa.Check(np.isfinite, element_wise=True)
    nonnegative = [pa.Check.ge(0), finite]
    return pa.DataFrameSchema(
        {
            "cluster": pa.Column(int, [pa.Check.ge(0)], unique=True, coerce=True),
            "vertices": pa.Column(int, pa.Check.ge(0), coerce=True),
            "eta": pa.Column(float, [pa.Check.ge(1.0), pa.Check.le(3.0)], coerce=True),
            "sigma_s": pa.Column(float, [pa.Check.gt(0), pa.Check.le(1.0)], coerce=True),
            "sigma_ss": pa.Column(float, [pa.Check.gt(0), pa.Check.le(1.0)], coerce=True),
            "rho_s": pa.Column(float, nonnegative, coerce=True),
            **{f"rho_ss_{c}": pa.Column(float, nonnegative, coerce=True) for c in "rgb"},
            "samples": pa.Column(int, pa.Check.ge(0), coerce=True),  # 0: a cluster without a usable sample
            "loss": pa.Column(float, nonnegative, coerce=True),
            "model": pa.Column(int, pa.Check.isin(sorted(MODEL_NAMES)), coerce=True),
        },
        strict=True, ordered=True, name="lobes.csv",
    )



def read_lobes(directory: Path):
    """The cluster labels (N,) and lobes (list of :class:`sellip.fit.lobes.ClusterLobe`, cluster order) of a
    ``cluster-lobes`` output directory. ValueError naming the file when it is missing or invalid."""
    import pandas as pd
    import pandera.pandas as pa

    from sellip.fit.lobes import ClusterLobe

    directory = Path(directory)
    labels_path, lobes_path = directory / "labels.npy", directory / "lobes.csv"
    for path in (labels_path, lobes_path):
        if not path.is_file():
            raise ValueError(f"{path}: missing; run `sellip cluster-lobes` first")
    labels = np.load(labels_path)
    try:
        table = lobes_schema().validate(pd.read_csv(lobes_path), lazy=True)
    except pa.errors.SchemaErrors as error:
        first = error.failure_cases.iloc[0]
        raise ValueError(f"{lobes_path}: invalid ({len(error.failure_cases)} problems; first: column "
                         f"{first['column']!r}, check {first['check']!r}, value {first['failure_case']!r})") from None
    table = table.sort_values("cluster")
    if list(table["cluster"]) != list(range(len(table))):
        raise ValueError(f"{lobes_path}: clusters must be numbered 0..K-1, got {list(table['cluster'])}")
    if (labels.ndim != 1 or labels.dtype.kind != "i"
            or (labels.size and (labels.min() < 0 or labels.max() >= len(table)))):
        raise ValueError(f"{labels_path}: expected (N,) integer labels in 0..{len(table) - 1}")
    lobes = [ClusterLobe(eta=row.eta, sigma_s=row.sigma_s, sigma_ss=row.sigma_ss, rho_s=row.rho_s,
                         rho_ss=np.array([row.rho_ss_r, row.rho_ss_g, row.rho_ss_b]), samples=int(row.samples),
                         loss=row.loss, theta_h_deg=np.zeros(0), value=np.zeros(0))
             for row in table.itertuples(index=False)]
    return labels, lobes



def read_labels(directory: Path, count: int | None = None) -> np.ndarray | None:
    """``labels.npy`` of a cluster-lobes directory: (N,) int64, the cluster of every vertex; None where ``count`` is
    given and it labels another number of vertices (another mesh: a caller then goes without)."""
    labels = np.load(Path(directory) / "labels.npy").astype(np.int64)
    return None if count is not None and labels.shape != (count,) else labels


def previous_labels(run: Path, iteration: int) -> np.ndarray | None:
    """The clusters of pass ``iteration - 1`` of the results folder ``run`` (``iter/N-1/clusters/labels.npy``), as the
    workflow gives cluster_lobes (the hysteresis of :func:`sellip.fit.clusters.cluster_materials`); None at pass 0
    or where that directory is missing."""
    directory = Path(run) / "iter" / str(int(iteration) - 1) / "clusters"
    return read_labels(directory) if iteration > 0 and (directory / "labels.npy").is_file() else None


def pass_clusters(run: Path) -> list[tuple[Path, dict]]:
    """Every pass's ``iter/<it>/clusters/clusters.json`` of the results folder ``run``, in pass order: (path, its
    parsed record); empty where no pass has clustered yet."""
    import json

    paths = sorted(Path(run).glob("iter/*/clusters/clusters.json"), key=lambda path: int(path.parent.parent.name))
    return [(path, json.loads(path.read_text())) for path in paths]


def read_models(directory: Path, count: int | None = None) -> np.ndarray:
    """The model of every vertex (N,) uint8 (``models.npy``) of a ``cluster-lobes`` output directory.
    ValueError naming the file when it is missing, not (N,) codes of :data:`sellip.model.params.MODEL_NAMES`,
    or (with ``count``) not ``count`` long."""
    from sellip.model.params import MODEL_NAMES

    path = Path(directory) / "models.npy"
    if not path.is_file():
        raise ValueError(f"{path}: missing; run `sellip cluster-lobes` first")
    models = np.load(path)
    if models.ndim != 1 or models.dtype.kind not in "iu" or not np.isin(models, sorted(MODEL_NAMES)).all():
        raise ValueError(f"{path}: expected (N,) integer model codes in {sorted(MODEL_NAMES)}")
    if count is not None and len(models) != count:
        raise ValueError(f"{path}: {len(models)} models for {count} vertices")
    return models.astype(np.uint8)



def recorded_fit_settings(clusters_json: dict, path: Path | str = "clusters.json"):
    """The :class:`sellip.fit.records.FitSettings` of a pass's lobe fits, as its ``clusters.json`` (parsed, read from
    ``path``) records them: the workflow's ``fit.settings`` for that pass. Raises ValueError for a file written before
    they were recorded (2026-11-26), naming the job to run again."""
    from sellip.fit.records import FitSettings

    if "fit_settings" not in clusters_json:
        raise ValueError(f"{path} has no fit_settings (written before 2026-11-26): run its cluster_lobes job again "
                         f"(snakemake --forcerun cluster_lobes --notemp ...)")
    return FitSettings(**clusters_json["fit_settings"])



def clustering_settings(clusters_json: dict, overrides: dict | None = None):
    """The :class:`sellip.fit.clusters.AugmentSettings` a ``clusters.json`` (its parsed dict) was made with,
    ``overrides`` (field: value) over them: how a replay re-runs a pass's clustering or lobe fit as the workflow ran it
    (the :class:`sellip.fit.records.FitSettings` of the lobe fit are its ``fit_settings``)."""
    from sellip.fit.clusters import AugmentSettings

    fields = {f.name for f in dataclasses.fields(AugmentSettings)}
    unknown = set(overrides or {}) - fields
    if unknown:
        raise ValueError(f"not AugmentSettings fields: {sorted(unknown)}; expected some of {sorted(fields)}")
    return AugmentSettings(**{**{k: v for k, v in clusters_json["settings"].items() if k in fields},
                              **(overrides or {})})



def load_rows(group, rows: np.ndarray):
    """Observations (:class:`sellip.fit.records.Observations`) of the store rows ``rows`` (sorted), reading only their
    chunks."""
    from sellip.fit.observe import PER_VIEW_ARRAYS, VIEW_AXES
    from sellip.fit.records import Observations

    data = {name: np.asarray(group[name].oindex[rows]) for name in PER_VIEW_ARRAYS}
    for name in VIEW_AXES:
        data[name] = np.repeat(np.asarray(group[name][...])[None], len(rows), axis=0)
    return Observations(**data)



def plot_lobes(path: Path, lobes, color_of, models=None) -> None:
    """lobes.png: per cluster, its samples and its lobe (mono, per unit shading) against theta_h;
    ``models`` (K,) the clusters' model codes, shown in the titles."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sellip.fit.lobes import lobe_curve

    columns = min(len(lobes), 4)
    rows = -(-len(lobes) // columns)
    figure, axes = plt.subplots(rows, columns, figsize=(4 * columns, 3.2 * rows), squeeze=False)
    theta = np.linspace(0, 89.5, 180)
    for k, (axis, lobe) in enumerate(zip(axes.ravel(), lobes)):
        axis.scatter(lobe.theta_h_deg, lobe.value, s=2, color="k", alpha=0.3, label="samples")
        axis.plot(theta, lobe_curve(theta, lobe, color_of(k)), color="r", label="cluster lobe")
        axis.set_yscale("symlog", linthresh=1e-3)
        lobes_text = {0: "no lobe", 1: f"σs {lobe.sigma_s:.3f}"}.get(
            -1 if models is None else int(models[k]), f"σs {lobe.sigma_s:.3f}, σss {lobe.sigma_ss:.2f}")
        model_text = "" if models is None else f" (model {int(models[k])})"
        axis.set_title(f"cluster {k}{model_text}: {lobes_text}, η {lobe.eta:.2f}", fontsize=9)
        axis.set_xlabel("θh (deg)")
        axis.set_xlim(0, 90)
    for axis in axes.ravel()[len(lobes):]:
        axis.axis("off")
    axes[0, 0].set_ylabel("reflectance per unit shading")
    axes[0, 0].legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)
