"""The batched Levenberg-Marquardt of the per-vertex fit (JAX): damping, steps, rounds, the
roughness starts, the diffuse eta hold's constants; each vertex an independent small problem (paper §4.3,
docs/design.md §5, §7) over 5 nonlinear unknowns (normal offset (2), eta, sigma_s, sigma_ss).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from sellip.fit.kernels import kernel
from sellip.fit.parameterization import Frame, decode_parameters, encode_parameters, eta_from
from sellip.fit.records import FitSettings
from sellip.fit.residuals import (
    Vertex,
    fixed_sigma_ss,
    lobe_terms,
    residuals_and_jacobian,
    residuals_from_terms,
    solve_spd,
    view_terms,
)

# --- Levenberg-Marquardt --------------------------------------------------------------------

class _LMState(NamedTuple):
    """Per-vertex solver state, batch-first. The normal equations (J^T J, J^T r) at z are carried:
    the Jacobian is computed at each trial point together with its residuals, and kept when the
    step is accepted."""

    z: jnp.ndarray  # (N, 5) unconstrained parameters
    loss: jnp.ndarray  # (N,)
    damping: jnp.ndarray  # (N,)
    iterations: jnp.ndarray  # (N,) int32, in the current stage
    done: jnp.ndarray  # (N,) bool
    hess: jnp.ndarray  # (N, F, F) J^T J over the free columns
    grad: jnp.ndarray  # (N, F) J^T r
    mark: jnp.ndarray  # (N,) the loss PROGRESS_ITERATIONS iterations ago (see lm_rounds)
    fits: jnp.ndarray  # (N, F) 1 for the free columns this vertex moves in this stage (fitted_columns)
    limit: jnp.ndarray  # (N,) int32 the stage's iteration cap


def free_parameters(settings: FitSettings) -> tuple[int, ...]:
    """Indices into z of the parameters LM may move: normal (0, 1), eta (2), sigma_s (3), sigma_ss (4).

    A fixed sigma_ss is never moved, nor the roughness of a lobe the model (``settings.lobes``)
    leaves out; with ``settings.fit_normal`` False the normal stays at normal0. Which of these
    columns a vertex moves in a stage is data (:func:`fitted_columns`).
    """
    normal = (0, 1) if settings.fit_normal else ()
    if settings.lobes == "diffuse":
        return normal + (2,)
    if settings.lobes == "specular" or settings.sigma_ss_fixed is not None:
        return normal + (2, 3)
    return normal + (2, 3, 4)


Z_LIMIT = 6.0
"""The largest |z| of the sigmoid-bounded parameters (eta, sigma_s, sigma_ss) LM moves to."""
PROGRESS_ITERATIONS = 4
STUCK_DAMPING = 10.0
"""LM stops a vertex whose loss fell by less than the tolerance over PROGRESS_ITERATIONS
iterations with its damping above STUCK_DAMPING (:func:`lm_rounds`)."""


def _loss_tolerance(settings: FitSettings, dtype) -> float:
    """Relative loss decrease below which the fit has converged: settings.tolerance, but never
    below what the dtype resolves (float32 losses stop improving near 1e-6)."""
    return max(settings.tolerance, 30 * float(jnp.finfo(dtype).eps))


def _normal_equations(z, v: Vertex, frame: Frame, settings: FitSettings, free: tuple[int, ...], fits):
    """(loss, J^T J (F, F), J^T r (F,)) of one vertex at z; the columns it does not move (``fits`` (F,) 0) are 0."""
    r, jac = residuals_and_jacobian(z, v, frame, settings, free)
    jac = jac * fits
    return jnp.sum(r * r), jac.T @ jac, jac.T @ r


def _lm_step(state: _LMState, v: Vertex, frame: Frame, settings: FitSettings, free: tuple[int, ...]):
    """One Levenberg-Marquardt step of one vertex (unbatched ``state``) over the parameters ``free``.

    A fresh state (loss +inf, :func:`run_lm`) takes no step: its first "step" evaluates the normal
    equations at the start and always accepts them (and ends the fit if they are not finite), so
    that one compiled kernel serves the start and the iterations.
    Returns (z, loss, damping, hess, grad, converged, fresh)."""
    z, loss, damping, hess, grad = state.z, state.loss, state.damping, state.hess, state.grad
    fresh = jnp.isinf(loss)
    fitted = state.fits  # (F,) 0: a column held (a roughness the model lacks, or held in this stage)
    basis = jnp.eye(5, dtype=z.dtype)[np.asarray(free)]  # (F, 5)
    diag = jnp.diag(hess) + 1e-9

    def solve(moving):  # the damped step with the columns where ``moving`` is 0 held
        held = jnp.diag(1 - moving)
        return -solve_spd((hess + damping * jnp.diag(diag)) * moving[:, None] * moving[None, :] + held,
                          grad * moving) @ basis

    # Bounded parameters stay where their sigmoid still moves (|z| <= Z_LIMIT: within 0.25 % of
    # the range of a bound; a saturated one would leave a zero Jacobian column for good). A step
    # that would cross the limit is taken again with those parameters held (a projected step),
    # so that the quadratic model stays true to the step taken.
    step = solve(fitted)
    limit = jnp.asarray([np.inf, np.inf, Z_LIMIT, Z_LIMIT, Z_LIMIT], z.dtype)
    crossing = (jnp.abs(z + step) > limit).astype(z.dtype) @ basis.T  # (F,) 1 where the step crosses
    step = jnp.where(jnp.any(crossing > 0), solve(fitted * (1 - crossing)), step)
    z_new = jnp.where(fresh, z, jnp.clip(z + step, -limit, limit))
    loss_new, hess_new, grad_new = _normal_equations(z_new, v, frame, settings, free, fitted)
    better = (jnp.isfinite(loss_new) & (loss_new < loss) & jnp.all(jnp.isfinite(hess_new))
              & jnp.all(jnp.isfinite(grad_new)))
    tolerance = _loss_tolerance(settings, z.dtype)
    rel_gain = (loss - loss_new) / jnp.maximum(loss, jnp.finfo(z.dtype).tiny)
    # Stationarity at z (MINPACK's gtol): the largest cosine between the residual and a Jacobian column.
    cosine = jnp.max(jnp.abs(grad) / jnp.sqrt(diag * jnp.maximum(loss, jnp.finfo(z.dtype).tiny)))
    stationary = cosine < max(settings.gradient_tolerance, 10 * float(jnp.finfo(z.dtype).eps) ** 0.5)
    # Converged when the gain is small: the gain achieved by a near Gauss-Newton step (a heavily
    # damped step is small anyway), or the most the Gauss-Newton model at z can still give,
    # g^T H^-1 g (it ends the fits left crawling along a flat valley, e.g. a vanishing lobe whose
    # roughness runs to its bound, where steps fail by round-off and only the damping grows).
    model_gain = grad @ solve_spd(hess + 1e-6 * jnp.diag(diag) + jnp.diag(1 - fitted), grad) / jnp.maximum(
        loss, jnp.finfo(z.dtype).tiny)
    flat = (better & (rel_gain < tolerance) & (damping < 1e-2)) | (model_gain < tolerance)
    converged = stationary | flat | (loss_new < 1e-14)
    stalled = (~better) & (damping > 1e8)
    pick = lambda new, old: jnp.where(better, new, old)
    damping = jnp.where(fresh, damping, jnp.where(better, damping * 0.3, damping * 4.0))
    return (pick(z_new, z), pick(loss_new, loss), damping, pick(hess_new, hess), pick(grad_new, grad),
            jnp.where(fresh, ~better, converged | stalled), fresh)


@kernel(static_argnames=("settings", "steps", "free"))
def lm_rounds(state: _LMState, records: Vertex, frames: Frame, settings: FitSettings, steps: int,
               free: tuple[int, ...]) -> _LMState:
    """Up to ``steps`` LM iterations for a batch, stopping early when every vertex is done. Which
    columns each vertex moves and its iteration cap are data (``state.fits``, ``state.limit``): both
    stages of a fit share one compiled kernel per batch shape."""
    step = jax.vmap(lambda st, v, f: _lm_step(st, v, f, settings, free))
    tolerance = _loss_tolerance(settings, state.z.dtype)

    def body(carry):
        st, count = carry
        z, loss, damping, hess, grad, converged, fresh = step(st, records, frames)
        active = ~st.done
        pick = lambda new, old: jnp.where(active.reshape((-1,) + (1,) * (new.ndim - 1)), new, old)
        iterations = st.iterations + (active & ~fresh).astype(jnp.int32)
        loss = pick(loss, st.loss)
        # No progress: less than the tolerance gained over the last PROGRESS_ITERATIONS iterations
        # while the damping has grown past STUCK_DAMPING (a fit crawling along a flat valley, short
        # steps failing by round-off; a few failed steps at low damping only mean a poor model).
        check = active & (iterations % PROGRESS_ITERATIONS == 0)
        stuck = check & ((st.mark - loss) < tolerance * st.mark) & (damping > STUCK_DAMPING)
        st = _LMState(pick(z, st.z), loss, pick(damping, st.damping), iterations,
                      st.done | (active & (converged | stuck | (iterations >= st.limit))),
                      pick(hess, st.hess), pick(grad, st.grad), jnp.where(check, loss, st.mark), st.fits, st.limit)
        return st, count + 1

    def cond(carry):
        st, count = carry
        return (count < steps) & jnp.any(~st.done)

    return jax.lax.while_loop(cond, body, (state, jnp.asarray(0)))[0]


HOLD_ROUNDS = 2
"""With ``hold_diffuse_eta``: LM rounds after the second stage for the vertices whose eta moved by more than
HOLD_ETA_TOLERANCE from the one their diffuse transmissions held (each round holds the last result)."""
HOLD_ETA_TOLERANCE = 0.002

ROUGHNESS_GRID = ((0.05, 0.6), (0.1, 0.6), (0.2, 0.6), (0.3, 0.6), (0.45, 0.6),
                  (0.05, 0.9), (0.1, 0.9), (0.2, 0.9), (0.3, 0.9), (0.45, 0.9))
"""(sigma_s, sigma_ss) starting points tried besides the warm start: GGX lobes make the loss
non-convex in roughness."""


@kernel(static_argnames=("settings",))
def pick_best_start(z0, records: Vertex, frames: Frame, settings: FitSettings):
    """Per vertex, the lowest-loss start among the warm start and :data:`ROUGHNESS_GRID`. (N, 5).

    The starts differ in roughness only: the view terms are evaluated once per vertex."""
    grid = jnp.asarray(ROUGHNESS_GRID, z0.dtype)
    eta = eta_from(z0[:, 2])
    grid_starts = jax.vmap(lambda e: encode_parameters(jnp.full(len(ROUGHNESS_GRID), e), grid[:, 0], grid[:, 1],
                                                       z0.dtype))(eta)
    starts = jnp.concatenate([z0[:, None], grid_starts.at[:, :, :2].set(z0[:, None, :2])], axis=1)

    def losses(zs, v, f):
        fixed = fixed_sigma_ss(v, settings)
        normal, eta, _, _ = decode_parameters(zs[0], f, fixed)
        view = view_terms(normal, eta, v)
        _, _, sigma_s, sigma_ss = jax.vmap(lambda zz: decode_parameters(zz, f, fixed))(zs)
        return jax.vmap(lambda s, ss: jnp.sum(residuals_from_terms(lobe_terms(view, s, ss, v, settings.lobes), v,
                                                                    settings) ** 2))(sigma_s, sigma_ss)

    loss = jax.vmap(losses)(starts, records, frames)
    loss = jnp.where(jnp.isfinite(loss), loss, jnp.inf)
    return jnp.take_along_axis(starts, jnp.argmin(loss, axis=1)[:, None, None], 1)[:, 0]


def bucket(count: int, minimum: int = 64) -> int:
    """Sizes are rounded up to powers of two so that a few compiled shapes serve every call."""
    return max(minimum, 1 << int(np.ceil(np.log2(max(count, 1)))))


def _take(tree, index):
    return jax.tree_util.tree_map(lambda x: x[index], tree)


def to_host(tree):
    """Every leaf of ``tree`` as a numpy array: the LM's per-batch gathers are then numpy indexing
    (microseconds), not one dispatched JAX gather per field and batch."""
    return jax.tree_util.tree_map(np.asarray, tree)


_VIEW_FIELDS = ("obs_d", "obs_a", "obs_s", "to_light", "to_camera", "light_distance", "camera_up", "light_axis",
                "weight", "frames")
"""The fields of :class:`Vertex` with a view axis (axis 1 of a batch)."""


def view_bucket(count: int) -> int:
    """16, 24, 32, 48, 64, 96, 128, ...: at most 50 % padding, few distinct shapes."""
    size = 16
    while size < count:
        size = size * 3 // 2 if (size & (size - 1)) == 0 else size * 4 // 3
    return size


def _batches(active: np.ndarray, views: np.ndarray, batch: int):
    """Batches of ``batch`` vertex indices from ``active`` and the view slots each needs.

    Vertices are ordered by their number of used views, so each batch can drop the slots none of
    its vertices uses (views are at the front, :func:`_compact_views`); widths are rounded by
    :func:`view_bucket` (few compiled shapes). A last batch of at most a quarter of ``batch`` is
    padded to that quarter, any other to ``batch``: the vertices still running after most have
    converged are few, and two sizes compile half the kernels that every power of two down to 64
    would, for about 6 % more lanes stepped. Short batches repeat their vertices (identical work,
    harmless writes). Yields (index (size,), width)."""
    order = active[np.argsort(views[active], kind="stable")]
    for start in range(0, order.size, batch):
        size = batch if order.size - start > batch // 4 else batch // 4
        index = np.resize(order[start:start + size], size)
        yield index, view_bucket(int(views[index].max(initial=1)))


def _take_records(records: Vertex, index: np.ndarray, width: int) -> Vertex:
    """Rows ``index`` of a batch of records, with only the first ``width`` view slots."""
    rows = _take(records, index)
    if width >= rows.obs_d.shape[1]:
        return rows
    return rows._replace(**{name: jax.tree_util.tree_map(lambda x: x[:, :width], getattr(rows, name))
                            for name in _VIEW_FIELDS if getattr(rows, name) is not None})


def map_batches(kernel, rows: np.ndarray, records: Vertex, frames: Frame, batch: int, *per_vertex, out=None):
    """Apply a jitted batch ``kernel(*per_vertex_rows, records_rows, frames_rows)`` to the vertices
    ``rows``, in the view-width batches of :func:`_batches`, and scatter its outputs (a tuple or
    dict of per-vertex arrays) into ``out`` (same structure, full length; zeros when None). An output
    with a view axis narrower than ``out``'s is written to its first slots."""
    views = np.sum(np.asarray(records.weight) > 0, axis=1)
    for index, width in _batches(rows, views, batch):
        part = kernel(*[jnp.asarray(np.asarray(x)[index]) for x in per_vertex], _take_records(records, index, width),
                      _take(frames, index))
        part = jax.tree_util.tree_map(np.asarray, part)
        if out is None:
            n = len(records.weight)
            out = jax.tree_util.tree_map(lambda x: np.zeros((n,) + x.shape[1:], x.dtype), part)  # noqa: B023 - called in this iteration

        def scatter(full, new, index=index):
            full[(index,) + tuple(slice(0, k) for k in new.shape[1:])] = new
        jax.tree_util.tree_map(scatter, out, part)
    return out


def fitted_columns(records: Vertex, free: tuple[int, ...], hold_lobes: bool = False) -> np.ndarray:
    """(N, F) 1 for the columns of ``free`` each vertex moves: those its model fits (not the roughness
    of a lobe it lacks, nor a fixed sigma_ss; every column without per-vertex models), without the
    roughnesses when ``hold_lobes`` (the first stage, while the normal may still be a few degrees off:
    a sharp lobe would otherwise collapse onto one bright view)."""
    n = len(records.weight)
    dtype = np.asarray(records.weight).dtype
    if records.lobe_mask is None:
        per_parameter = [np.ones(n)] * 5
    else:
        lobe_mask = np.asarray(records.lobe_mask)
        per_parameter = [np.ones(n)] * 3 + [lobe_mask[:, 0], lobe_mask[:, 1] * np.isnan(records.sigma_ss_fixed)]
    if hold_lobes:
        per_parameter[3] = per_parameter[4] = np.zeros(n)
    return np.stack([per_parameter[i] for i in free], -1).astype(dtype)


def run_lm(z, records: Vertex, frames: Frame, settings: FitSettings, run: np.ndarray, max_iterations: int,
            hold_lobes: bool = False):
    """LM over the parameters :func:`free_parameters` ``(settings)`` (the roughnesses held when
    ``hold_lobes``) to convergence for the vertices where ``run`` is set, with compaction.

    The vertices still running are gathered into batches of one fixed size (one compiled shape
    per view width, :func:`_batches`) and advanced ``round_iterations`` steps at a time, so the
    cost follows the mean number of iterations, not the slowest vertex of a chunk, and the number
    of views each vertex uses, not the most any vertex uses. Returns (z, loss, iterations, hess)
    as numpy arrays; hess (N, F, F) is J^T J at z over the free columns (those held are 0).
    """
    free = free_parameters(settings)
    z = np.asarray(z)
    n = z.shape[0]
    dtype = z.dtype
    run = np.asarray(run, bool)
    views = np.sum(np.asarray(records.weight) > 0, axis=1)
    batch = min(settings.lm_batch, bucket(n))
    # A fresh state (loss +inf): the first step of each vertex evaluates its normal equations (_lm_step).
    loss = np.full(n, np.inf, dtype)
    hess = np.zeros((n, len(free), len(free)), dtype)
    grad = np.zeros((n, len(free)), dtype)
    state = _LMState(z, loss, np.full(n, 1e-3, dtype), np.zeros(n, np.int32), ~run, hess, grad, loss.copy(),
                     fitted_columns(records, free, hold_lobes), np.full(n, max_iterations, np.int32))
    while True:
        active = np.flatnonzero(~state.done)
        if active.size == 0:
            return state.z, state.loss, state.iterations, state.hess
        fields = [x.copy() for x in state]
        for index, width in _batches(active, views, batch):
            part = lm_rounds(_take(state, index), _take_records(records, index, width), _take(frames, index),
                              settings, steps=settings.round_iterations, free=free)
            for full, new in zip(fields, part):
                full[index] = np.asarray(new)
        state = _LMState(*fields)


