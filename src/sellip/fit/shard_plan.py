"""How the fit's vertices are split into shards (rule ``fit_pbrdf``'s scatter), without JAX: each shard's vertex
rows (:func:`shard_rows`), the memory one shard's job needs (:data:`SHARD_MEMORY`), and the shard count the workflow
plans before it runs (:func:`planned_shards`: config ``fit.shards`` raised to what ``fit.mem_mb`` holds). The
workflow imports this module when it reads its config, so it stays free of JAX and the fit's own modules.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

from sellip import workflow_support


def shard_rows(num_vertices: int, chunk: int, index: int, total: int) -> tuple[int, int]:
    """Vertex range [start, stop) of shard ``index`` (0-based) of ``total``, in whole chunks."""
    blocks = -(-num_vertices // chunk)
    first, last = index * blocks // total, (index + 1) * blocks // total
    return min(first * chunk, num_vertices), min(last * chunk, num_vertices)


def largest_shard(num_vertices: int, chunk: int, total: int) -> int:
    """Vertices of the largest of ``total`` shards (:func:`shard_rows`)."""
    return max(stop - start for start, stop in (shard_rows(num_vertices, chunk, k, total) for k in range(total)))


@dataclasses.dataclass(frozen=True)
class ShardMemory:
    """Peak resident memory of one ``sellip fit`` job, in bytes: ``base`` (Python, JAX, the compiled kernels) +
    ``loaded`` per (vertex, view) of the shard (its observations, read whole) + ``working`` per (vertex, view) of
    one chunk of ``FitSettings.chunk_size`` vertices (the fit's arrays)."""

    base: float
    loaded: float
    working: float

    def bytes(self, vertices: int, views: int, chunk_size: int) -> float:
        """Bytes a job fitting ``vertices`` vertices of ``views`` views needs."""
        return self.base + views * (self.loaded * vertices + self.working * min(vertices, chunk_size))

    def shards_for(self, total_vertices: int, views: int, chunk_size: int, budget: float,
                   vertex_chunk: int = 1) -> int | None:
        """The fewest shards of ``total_vertices`` whose largest job fits in ``budget`` bytes; None if none does.
        Shards are whole store chunks of ``vertex_chunk`` vertices (:func:`largest_shard`)."""
        blocks = max(-(-total_vertices // vertex_chunk), 1)

        def fits(shards: int) -> bool:
            return self.bytes(largest_shard(total_vertices, vertex_chunk, shards), views, chunk_size) <= budget

        low, high = 1, blocks
        if not fits(high):
            return None
        while low < high:  # the bytes fall as the shards grow: the first count that fits
            middle = (low + high) // 2
            low, high = (low, middle) if fits(middle) else (middle + 1, high)
        return low


SHARD_MEMORY = ShardMemory(base=0.5e9, loaded=40.0, working=3600.0)
"""Measured with benchmarks/shard_memory.py at 36 views (docs/reliability.md, "Memory of a fit shard"): peaks of
0.70, 1.25 and 1.36 GB at 4k, 33k and 131k vertices (0.96 GB for a first job, which compiles), fitted by a base of
0.17 GB, 31 B per loaded and 3,541 B per chunk vertex-view; the base here includes compiling and the rest is
rounded up: the model predicts 1.29x what was measured above one chunk."""


class ShardMemoryError(MemoryError):
    """A fit shard that does not fit in the memory its job may use; the message says how many shards would."""


def planned_shards(requested: int, vertices: int, views: int, chunk_size: int, mem_mb: float, vertex_chunk: int,
                   model: ShardMemory = SHARD_MEMORY) -> tuple[int, str | None]:
    """(shard count, why it was raised or None): config ``fit.shards`` (``requested``), raised to the fewest shards
    whose largest job the memory model says fits in ``mem_mb`` MB (config ``fit.mem_mb``) for a mesh of at most
    ``vertices`` vertices (``init.max_vertices``: every initial mesh is remeshed to at most that) observed in
    ``views`` views (those the observations keep), the fit preparing ``chunk_size`` vertices at a time, the
    observation store chunked by ``vertex_chunk`` vertices. The fit job checks its own shard against the memory it
    may use before it reads (:func:`sellip.fit.shard.fit_shard`); this plans the count so that it need not fail.
    Raises :class:`ShardMemoryError` when no count fits: a shard of one store chunk needs more than ``mem_mb``."""
    budget = mem_mb * 1e6
    needed = model.shards_for(vertices, views, chunk_size, budget, vertex_chunk)
    if needed is None:
        smallest = largest_shard(vertices, vertex_chunk, max(-(-vertices // vertex_chunk), 1))
        floor = model.bytes(smallest, views, chunk_size)
        raise ShardMemoryError(
            f"config fit.mem_mb {mem_mb:,.0f} MB is less than one fit job needs at any shard count: about "
            f"{floor / 1e9:.2f} GB for the smallest shard, {smallest:,} vertices (one chunk of the observations, "
            f"observe.vertex_chunk) over {views} views. Raise fit.mem_mb to {math.ceil(floor / 1e6 / 100) * 100:,} "
            "or more, or lower fit.settings.chunk_size and observe.vertex_chunk (docs/reliability.md, \"Memory of a "
            "fit shard\")")
    if needed <= requested:
        return requested, None
    per_shard = model.bytes(largest_shard(vertices, vertex_chunk, needed), views, chunk_size)
    return needed, (f"fit.shards {requested} raised to {needed}: {vertices:,} vertices (init.max_vertices) of {views} "
                    f"views need about {per_shard / 1e9:.2f} GB per fit job at {needed} shards, and fit.mem_mb is "
                    f"{mem_mb:,.0f} MB (the memory model, docs/reliability.md)")


def fit_shard_plan(config: Mapping, schema: Mapping, view_ids: list[str] | None) -> tuple[int, str | None]:
    """(the fit's scatter count, why it was raised or None) before anything runs: config ``fit.shards`` raised to
    what ``fit.mem_mb`` holds by the memory model (:func:`planned_shards`), for at most
    ``init.max_vertices`` vertices and the views the observations keep (``view_ids`` of the capture, or None: the
    capture cannot be read yet and its stage will say so; less ``evaluate.held_out_views``, at most
    ``observe.max_views``), at the largest ``chunk_size`` of any pass (``fit.settings``'s, or ``augment.settings``'
    and ``final.settings``' where they set it: they override the fit's in those passes). Raises
    :class:`ShardMemoryError` when no count fits."""
    requested = int(config["fit"]["shards"])
    if view_ids is None:
        return requested, None
    held_out = set((config.get("evaluate") or {}).get("held_out_views") or ())
    views = sum(view not in held_out for view in view_ids)
    max_views = workflow_support.declared_setting(config, schema, "observe.max_views")
    if max_views:
        views = min(views, int(max_views))
    chunks = []
    for section in ("fit", "augment", "final"):
        value = ((config.get(section) or {}).get("settings") or {}).get("chunk_size")
        if section == "fit" and value is None:
            value = workflow_support.declared_setting(config, schema, "fit.settings.chunk_size")
        chunks.extend(value if isinstance(value, list) else [value])
    vertices = int(workflow_support.declared_setting(config, schema, "init.max_vertices"))
    vertex_chunk = int(workflow_support.declared_setting(config, schema, "observe.vertex_chunk"))
    return planned_shards(requested, vertices, max(views, 1), max(int(c) for c in chunks if c is not None),
                          float(config["fit"]["mem_mb"]), vertex_chunk)
