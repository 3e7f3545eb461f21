"""Per-tile alpha compositing as Pallas kernels (Triton on GPU, ``interpret=True`` on a CPU).

One program per tile, its pixels the vector lanes. The backward walks each tile back to front
writing one gradient row per pair, and :func:`reduce_pair_rows` sums each Gaussian's rows in a
fixed order: no atomics, bit-identical gradients.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl

from .binning import grid_shape, image_to_tiles, tiles_to_image
from .project import ALPHA_MAX, ALPHA_MIN, T_MIN

#: Pairs blended per iteration of a program's loop between "is the tile done?" tests.
PAIR_BATCH = 8
#: Gradient row layout per pair: d means2d (2), d conic (3), d opacity (1), d features (F).
_ROW_FIXED = 6


#: Whether the kernels are lowered for Triton off a GPU (a ContextVar: per thread/task).
_FOR_GPU = contextvars.ContextVar("jaxedit_pallas_for_gpu", default=False)


@contextlib.contextmanager
def compiled_for_gpu():
    """Within this context the kernels are lowered for Triton even off a GPU (``jax.export``)."""
    token = _FOR_GPU.set(True)
    try:
        yield
    finally:
        _FOR_GPU.reset(token)


def use_interpreter() -> bool:
    """Run the kernels in the Pallas interpreter: off a GPU, unless :func:`compiled_for_gpu`."""
    return jax.default_backend() != "gpu" and not _FOR_GPU.get()


def _triton_params(num_warps: int):
    """Triton compiler parameters (the import fails on jaxlibs without Pallas GPU support)."""
    from jax.experimental.pallas import triton as pltriton

    return pltriton.CompilerParams(num_warps=num_warps)


def _pixel_centres(tile_id, tiles_x: int, tile: int, dtype):
    """float [P] x and y pixel centres of tile ``tile_id`` (P = tile^2, row-major)."""
    lane = jnp.arange(tile * tile, dtype=jnp.int32)
    x = (tile_id % tiles_x) * tile + lane % tile
    y = (tile_id // tiles_x) * tile + lane // tile
    return x.astype(dtype) + 0.5, y.astype(dtype) + 0.5


def _load_pair(slot, gids_ref, m_ref, con_ref, op_ref):
    """Scalars of the Gaussian in pair ``slot``: (gid, mx, my, a, b, c, opacity)."""
    g = gids_ref[slot]
    return (g, m_ref[g, 0], m_ref[g, 1], con_ref[g, 0], con_ref[g, 1], con_ref[g, 2], op_ref[g])


def _alpha(mx, my, a, b, c, o, px, py):
    """dx, dy, exp(power), o exp(power) and alpha [P] of one Gaussian over the tile's pixels."""
    dx = mx - px
    dy = my - py
    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    vis = jnp.exp(jnp.minimum(power, 0.0))
    raw = o * vis
    alpha = jnp.minimum(ALPHA_MAX, raw)
    alpha = jnp.where((power > 0) | (alpha < ALPHA_MIN), 0.0, alpha)
    return dx, dy, vis, raw, alpha


def _forward_kernel(start_ref, gids_ref, m_ref, con_ref, op_ref, f_ref,
                    feat_ref, trans_ref, last_ref, *, tiles_x, tile, num_features, capacity):
    """One tile front to back -> feat_ref float [F, P], trans_ref float [P] (final T),
    last_ref int32 [P] (slot of the last blended pair, begin - 1 where none)."""
    t = pl.program_id(0)
    begin = start_ref[t]
    end = start_ref[t + 1]
    dtype = m_ref.dtype
    px, py = _pixel_centres(t, tiles_x, tile, dtype)
    n = tile * tile

    def one_pair(i, state):
        trans, alive, last, acc = state
        valid = i < end
        g, mx, my, a, b, c, o = _load_pair(jnp.minimum(i, capacity - 1), gids_ref, m_ref,
                                            con_ref, op_ref)
        alpha = _alpha(mx, my, a, b, c, o, px, py)[4]
        alpha = jnp.where(valid, alpha, 0.0)
        t_after = trans * (1.0 - alpha)
        stop = alive & (t_after < T_MIN)
        blend = alive & ~stop & (alpha > 0.0)
        w = jnp.where(blend, alpha * trans, 0.0)
        acc = tuple(acc[k] + w * f_ref[g, k] for k in range(num_features))
        trans = jnp.where(blend, t_after, trans)
        last = jnp.where(blend, i, last)
        return trans, alive & ~stop, last, acc

    def cond(carry):
        i, (_, alive, _, _) = carry
        return (i < end) & (jnp.max(alive.astype(jnp.int32)) > 0)

    def batch(carry):
        i, state = carry
        for k in range(PAIR_BATCH):  # unrolled: one "done?" test per batch of pairs
            state = one_pair(i + k, state)
        return i + PAIR_BATCH, state

    state = (jnp.ones((n,), dtype), jnp.ones((n,), jnp.bool_),
             jnp.full((n,), begin - 1, jnp.int32),
             tuple(jnp.zeros((n,), dtype) for _ in range(num_features)))
    _, (trans, _, last, acc) = jax.lax.while_loop(cond, batch, (begin, state))
    for k in range(num_features):
        feat_ref[k, :] = acc[k]
    trans_ref[...] = trans
    last_ref[...] = last


def _backward_kernel(start_ref, gids_ref, m_ref, con_ref, op_ref, f_ref, slots_ref, trans_ref,
                     last_ref, gf_ref, gt_ref, zeros_ref, rows_ref, *, tiles_x, tile,
                     num_features, capacity):
    """One tile back to front -> rows_ref float [N + PAIR_BATCH, ROW] (aliased to zeros_ref),
    from the forward's trans_ref [P], last_ref int32 [P], the upstream gf_ref float [F, P] and
    gt_ref [P], and the enumeration slots_ref int32 [N]."""
    del zeros_ref  # the output's initial (zero) contents
    t = pl.program_id(0)
    begin = start_ref[t]
    px, py = _pixel_centres(t, tiles_x, tile, m_ref.dtype)
    t_final = trans_ref[...]
    last = last_ref[...]
    g_f = tuple(gf_ref[k, :] for k in range(num_features))
    behind_final = gt_ref[...] * t_final  # g_T T_final: the final T is "behind" every pair
    stop = jnp.max(last)  # the tile's last contributing slot

    def one_pair(j, state):
        trans, behind = state  # T after pair i, and g . S_i + g_T T_final
        i = stop - j
        g, mx, my, a, b, c, o = _load_pair(i, gids_ref, m_ref, con_ref, op_ref)
        dx, dy, vis, raw, alpha = _alpha(mx, my, a, b, c, o, px, py)
        active = (i <= last) & (alpha > 0.0)
        one_minus = jnp.where(active, 1.0 - alpha, 1.0)
        t_before = trans / one_minus
        gdotf = sum(g_f[k] * f_ref[g, k] for k in range(num_features))
        d_alpha = t_before * gdotf - behind / one_minus
        d_raw = jnp.where(active & (raw < ALPHA_MAX), d_alpha, 0.0)
        d_pow = d_raw * raw
        w = jnp.where(active, alpha * t_before, 0.0)
        sdx, sdy = jnp.sum(d_pow * dx), jnp.sum(d_pow * dy)
        sxx, sxy, syy = jnp.sum(d_pow * dx * dx), jnp.sum(d_pow * dx * dy), jnp.sum(d_pow * dy * dy)
        dest = slots_ref[i]
        rows_ref[dest, 0] = -(a * sdx + b * sdy)
        rows_ref[dest, 1] = -(c * sdy + b * sdx)
        rows_ref[dest, 2] = -0.5 * sxx
        rows_ref[dest, 3] = -sxy
        rows_ref[dest, 4] = -0.5 * syy
        rows_ref[dest, 5] = jnp.sum(d_raw * vis)
        for k in range(num_features):
            rows_ref[dest, _ROW_FIXED + k] = jnp.sum(w * g_f[k])
        return jnp.where(active, t_before, trans), behind + w * gdotf

    jax.lax.fori_loop(0, jnp.maximum(stop - begin + 1, 0), one_pair, (t_final, behind_final))


def _specs(tile, num_features):
    """Block specs of the per-tile image arrays ([T, F, P], [T, P])."""
    p = tile * tile
    feat = pl.BlockSpec((None, num_features, p), lambda t: (t, 0, 0))
    pix = pl.BlockSpec((None, p), lambda t: (t, 0))
    return feat, pix


def _call(kernel, inputs, in_specs, out_shape, out_specs, num_programs, interpret, num_warps,
          aliases=None):
    return pl.pallas_call(
        kernel, out_shape=out_shape, grid=(num_programs,), in_specs=in_specs,
        out_specs=out_specs, input_output_aliases=aliases or {}, interpret=interpret,
        compiler_params=None if interpret else _triton_params(num_warps),
    )(*inputs)


def _whole():
    return pl.BlockSpec(memory_space=pl.ANY)


def _num_warps(tile: int) -> int:
    """One lane per pixel: a 16 x 16 tile is 8 warps of 32 threads (as gsplat's 256-thread blocks)."""
    return max(1, min(8, tile * tile // 32))


def tiles_forward(means2d, conics, opacities, features, gids, tile_start, width, height, tile,
                  interpret=False):
    """Forward kernel over all tiles -> (features float [T, F, P], transmittance float [T, P],
    last int32 [T, P]) from means2d float [C, 2], conics [C, 3], opacities [C], features
    [C, F], gids int32 [N] (by tile, depth; padding may hold C), tile_start int32 [T + 1]."""
    tiles_x, tiles_y = grid_shape(width, height, tile)
    num_tiles = tiles_x * tiles_y
    nf = features.shape[-1]
    p = tile * tile
    feat_spec, pix_spec = _specs(tile, nf)
    kernel = functools.partial(_forward_kernel, tiles_x=tiles_x, tile=tile, num_features=nf,
                               capacity=gids.shape[0])
    dtype = means2d.dtype
    out_shape = (jax.ShapeDtypeStruct((num_tiles, nf, p), dtype),
                 jax.ShapeDtypeStruct((num_tiles, p), dtype),
                 jax.ShapeDtypeStruct((num_tiles, p), jnp.int32))
    inputs = _padded_inputs(means2d, conics, opacities, features, gids, tile_start)
    return _call(kernel, inputs, [_whole()] * 6, out_shape, (feat_spec, pix_spec, pix_spec),
                 num_tiles, interpret, _num_warps(tile))


def _padded_inputs(means2d, conics, opacities, features, gids, tile_start):
    """Kernel inputs in the means' dtype, one zero-opacity Gaussian appended for padding slots."""
    def pad(x):
        x = x.astype(means2d.dtype)
        return jnp.concatenate([x, jnp.zeros((1,) + x.shape[1:], x.dtype)], 0)

    return (tile_start.astype(jnp.int32), gids.astype(jnp.int32), pad(means2d), pad(conics),
            pad(opacities), pad(features))


def row_width(num_features: int) -> int:
    """Columns of a gradient row: 6 + F rounded up to a power of two (Triton's block shapes)."""
    return 1 << (_ROW_FIXED + num_features - 1).bit_length()


def tiles_backward(means2d, conics, opacities, features, gids, tile_start, enum_slots, trans,
                   last, g_feat, g_trans, width, height, tile, interpret=False):
    """Backward kernel: float [N + PAIR_BATCH, ROW] gradient rows, row ``enum_slots[i]`` pair
    i's d means2d, d conic, d opacity, d features (zero-padded; unused rows zero). Arguments
    as :func:`tiles_forward`, plus ``enum_slots`` int32 [N], the forward's ``trans`` and
    ``last`` [T, P], and g_feat float [T, F, P], g_trans float [T, P]."""
    tiles_x, tiles_y = grid_shape(width, height, tile)
    num_tiles = tiles_x * tiles_y
    nf = features.shape[-1]
    feat_spec, pix_spec = _specs(tile, nf)
    kernel = functools.partial(_backward_kernel, tiles_x=tiles_x, tile=tile, num_features=nf,
                               capacity=gids.shape[0])
    inputs = _padded_inputs(means2d, conics, opacities, features, gids, tile_start)
    dtype = means2d.dtype
    zeros = jnp.zeros((gids.shape[0] + PAIR_BATCH, row_width(nf)), dtype)
    inputs += (enum_slots.astype(jnp.int32), trans, last, g_feat.astype(dtype),
               g_trans.astype(dtype), zeros)
    rows = jax.ShapeDtypeStruct(zeros.shape, dtype)
    specs = [_whole()] * 7 + [pix_spec, pix_spec, feat_spec, pix_spec, _whole()]
    return _call(kernel, inputs, specs, rows, _whole(), num_tiles, interpret, _num_warps(tile),
                 aliases={len(inputs) - 1: 0})


def _reduce_kernel(ends_ref, rows_ref, out_ref, *, width):
    """One Gaussian (k-th in depth order): the sum of its run of rows, PAIR_BATCH at a time,
    always in the same order. out_ref: float [ROW]."""
    k = pl.program_id(0)
    end = ends_ref[k]
    begin = jnp.where(k > 0, ends_ref[jnp.maximum(k - 1, 0)], 0)
    row = jax.lax.broadcasted_iota(jnp.int32, (PAIR_BATCH, width), 0)

    def batch(j, acc):
        first = begin + j * PAIR_BATCH
        block = rows_ref[pl.ds(first, PAIR_BATCH), :]
        return acc + jnp.where(first + row < end, block, 0.0)

    steps = (end - begin + PAIR_BATCH - 1) // PAIR_BATCH
    acc = jax.lax.fori_loop(0, steps, batch, jnp.zeros((PAIR_BATCH, width), rows_ref.dtype))
    out_ref[...] = jnp.sum(acc, axis=0)


def reduce_pair_rows(rows, depth_order, run_ends, interpret=False):
    """Per-Gaussian sums float [C, ROW] of ``rows`` [N + PAIR_BATCH, ROW] (:func:`tiles_backward`),
    with ``depth_order`` and ``run_ends`` int32 [C] of :class:`.binning.Bins`."""
    c, width = depth_order.shape[0], rows.shape[1]
    ends = jnp.minimum(run_ends, rows.shape[0] - PAIR_BATCH)  # an overflowed frame is redone
    sums = _call(functools.partial(_reduce_kernel, width=width), (ends.astype(jnp.int32), rows),
                 [_whole(), _whole()], jax.ShapeDtypeStruct((c, width), rows.dtype),
                 pl.BlockSpec((None, width), lambda k: (k, 0)), c, interpret, 1)
    return jnp.zeros_like(sums).at[depth_order].set(sums, unique_indices=True)


@functools.partial(jax.custom_vjp, nondiff_argnums=(5, 6, 7, 8))
def composite(means2d, conics, opacities, features, bins, width, height, tile,
              interpret=False):
    """:func:`.composite.composite` by the Pallas kernels, from the frame's
    :class:`.binning.Bins`; ``interpret``: use the Pallas interpreter."""
    return _composite_fwd(means2d, conics, opacities, features, bins, width, height, tile,
                          interpret)[0]


def _composite_fwd(means2d, conics, opacities, features, bins, width, height, tile, interpret):
    feat, trans, last = tiles_forward(means2d, conics, opacities, features, bins.gids,
                                      bins.tile_start, width, height, tile, interpret=interpret)
    out = (tiles_to_image(jnp.swapaxes(feat, 1, 2), width, height, tile),
           tiles_to_image(trans, width, height, tile))
    return out, (means2d, conics, opacities, features, bins, trans, last)


def _composite_bwd(width, height, tile, interpret, res, cts):
    means2d, conics, opacities, features, bins, trans, last = res
    g_feat, g_trans = cts
    g_feat = jnp.swapaxes(image_to_tiles(g_feat, width, height, tile), 1, 2)  # [T, F, P]
    g_trans = image_to_tiles(g_trans, width, height, tile)
    rows = tiles_backward(means2d, conics, opacities, features, bins.gids, bins.tile_start,
                          bins.enum_slots, trans, last, g_feat, g_trans, width, height, tile,
                          interpret=interpret)
    grads = reduce_pair_rows(rows, bins.depth_order, bins.run_ends, interpret=interpret)
    nf = features.shape[-1]
    return (grads[:, 0:2], grads[:, 2:5], grads[:, 5], grads[:, _ROW_FIXED:_ROW_FIXED + nf],
            None)


composite.defvjp(_composite_fwd, _composite_bwd)
