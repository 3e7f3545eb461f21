"""Exact per-tile alpha compositing in XLA, with a recomputing ``custom_vjp`` backward.

Each tile's depth-sorted pairs are cut into chunks of ``K`` blended in step by a ``lax.scan``;
a chunk's incoming transmittance comes from a segmented scan of the earlier chunks'.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from .binning import Bins, grid_shape, image_to_tiles, tiles_to_image
from .project import ALPHA_MAX, ALPHA_MIN, T_MIN

#: Pairs per chunk.
CHUNK = 32
#: Target (chunk, pixel) elements per scan block on a CPU: the working set stays in cache.
BLOCK_ELEMENTS = 8192
#: The same on an accelerator, where each block costs kernel launches.
BLOCK_ELEMENTS_ACCELERATOR = 1 << 22


def block_elements(platform: str) -> int:
    """(chunk, pixel) elements per block of the scan on ``platform`` ("cpu", "gpu", ...)."""
    return BLOCK_ELEMENTS if platform == "cpu" else BLOCK_ELEMENTS_ACCELERATOR


def layout(capacity: int, num_tiles: int, tile: int, chunk: int = CHUNK,
           block_elements: int = BLOCK_ELEMENTS) -> tuple[int, int]:
    """Static (number of blocks, chunks per block) for a buffer of ``capacity`` pairs."""
    per_block = max(1, block_elements // (tile * tile))
    nc = -(-capacity // chunk) + num_tiles
    nb = -(-nc // per_block)
    return nb, per_block


def make_chunks(bins: Bins, num_tiles: int, capacity: int, tile: int, chunk: int = CHUNK,
                block_elements: int = BLOCK_ELEMENTS):
    """Chunk layout of the sorted pairs: (gids int32 [NC, K] (-1 for padding), tile_of int32
    [NC] (num_tiles for unused), first bool [NC]: the chunk starts its tile's list)."""
    nb, per_block = layout(capacity, num_tiles, tile, chunk, block_elements)
    nc = nb * per_block
    start = bins.tile_start
    n_t = start[1:] - start[:-1]
    c_t = (n_t + chunk - 1) // chunk
    c_end = jnp.cumsum(c_t)
    c_begin = c_end - c_t
    j = jnp.arange(nc, dtype=jnp.int32)
    tile_of = jnp.searchsorted(c_end, j, side="right").astype(jnp.int32)
    used = tile_of < num_tiles
    t = jnp.minimum(tile_of, num_tiles - 1)
    first = used & (j == c_begin[t])
    idx = start[t][:, None] + (j - c_begin[t])[:, None] * chunk + jnp.arange(chunk, dtype=jnp.int32)
    ok = used[:, None] & (idx < start[t + 1][:, None])
    gids = jnp.where(ok, bins.gids[jnp.clip(idx, 0, bins.gids.shape[0] - 1)], -1)
    return gids, jnp.where(used, tile_of, num_tiles), first


def _seg_scan(values, first, op, identity):
    """Segmented exclusive scan along axis 0 (segments start where ``first``)."""

    def combine(a, b):
        fa, va = a
        fb, vb = b
        return fa | fb, jnp.where(fb.reshape(fb.shape + (1,) * (vb.ndim - fb.ndim)), vb, op(va, vb))

    _, incl = jax.lax.associative_scan(combine, (first, values))
    ident = jnp.full_like(values[:1], identity)
    shifted = jnp.concatenate([ident, incl[:-1]], 0)
    return jnp.where(first.reshape(first.shape + (1,) * (values.ndim - 1)), identity, shifted)


def _pixel_centres(tile_of, tiles_x, tile, dtype):
    """float [NC, P] x and y pixel centres of each chunk's tile (P = tile^2)."""
    o = jnp.arange(tile * tile, dtype=jnp.int32)
    tx = (tile_of % tiles_x) * tile
    ty = (tile_of // tiles_x) * tile
    px = (tx[:, None] + o[None] % tile).astype(dtype) + 0.5
    py = (ty[:, None] + o[None] // tile).astype(dtype) + 0.5
    return px, py


def _alpha(m, con, op, px, py):
    """One pair position across a block: dx, dy, exp(power), o exp(power), alpha [NB, P]
    from m [NB, 2], con [NB, 3], op [NB], px/py [NB, P]."""
    dx = m[:, 0, None] - px
    dy = m[:, 1, None] - py
    power = -0.5 * (con[:, 0, None] * dx * dx + con[:, 2, None] * dy * dy) - con[:, 1, None] * dx * dy
    vis = jnp.exp(jnp.minimum(power, 0.0))
    raw = op[:, None] * vis
    alpha = jnp.minimum(ALPHA_MAX, raw)
    alpha = jnp.where((power > 0) | (alpha < ALPHA_MIN), 0.0, alpha)
    return dx, dy, vis, raw, alpha


def _map_used(fn, xs, used_blocks, init):
    """``lax.map(fn, xs)`` over the first (traced) ``used_blocks`` blocks; others keep ``init``."""

    def body(b, outs):
        x = jax.tree_util.tree_map(lambda a: jax.lax.dynamic_index_in_dim(a, b, 0, False), xs)
        y = fn(x)
        return jax.tree_util.tree_map(
            lambda o, v: jax.lax.dynamic_update_index_in_dim(o, v, b, 0), outs, y)

    return jax.lax.fori_loop(0, used_blocks, body, init)


def _used_blocks(tile_of, nb, num_tiles):
    """int32 scalar: blocks holding at least one used chunk (used chunks are a prefix)."""
    per_block = tile_of.shape[0] // nb
    n_used = jnp.sum((tile_of < num_tiles).astype(jnp.int32))
    return (n_used + per_block - 1) // per_block


def _blocks(x, nb):
    """[NC, ...] -> [nb, NC / nb, ...]."""
    return x.reshape((nb, x.shape[0] // nb) + x.shape[1:])


def _block_params(means2d, conics, opacities, features, gids, nb):
    """Per-pair parameters as [nb, K, NB, ...] (padding pairs: opacity 0)."""
    gb = jnp.swapaxes(_blocks(gids, nb), 1, 2)  # [nb, K, NB]
    ok = gb >= 0
    g = jnp.where(ok, gb, 0)
    return means2d[g], conics[g], jnp.where(ok, opacities[g], 0.0), features[g]


def _local_products(xs):
    """Pass 1 on one block: product of (1 - alpha) over each chunk, [NB, P]."""
    m, con, op, px, py = xs

    def step(prod, x):
        return prod * (1.0 - _alpha(*x, px, py)[4]), None

    prod, _ = jax.lax.scan(step, jnp.ones(px.shape, px.dtype), (m, con, op))
    return prod


def _blend(xs):
    """Pass 2 on one block: features sum_i w_i f_i [NB, P, F] and last blended T [NB, P]."""
    m, con, op, f, px, py, carry = xs
    nf = f.shape[-1]

    def step(state, x):
        t, t_last, acc = state
        mk, ck, ok, fk = x
        alpha = _alpha(mk, ck, ok, px, py)[4]
        t_after = t * (1.0 - alpha)
        blended = t_after >= T_MIN  # a prefix of the list: T only decreases
        w = jnp.where(blended, alpha * t, 0.0)
        # One accumulator per channel keeps the pixel axis innermost (vectorised).
        acc = tuple(acc[j] + w * fk[:, j, None] for j in range(nf))
        return (t_after, jnp.where(blended, t_after, t_last), acc), None

    zeros = jnp.zeros_like(carry)
    (_, t_last, acc), _ = jax.lax.scan(step, (carry, jnp.ones_like(carry), (zeros,) * nf),
                                       (m, con, op, f))
    return jnp.stack(acc, -1), t_last


def _forward(means2d, conics, opacities, features, gids, tile_of, first, width, height, tile,
             block):
    tiles_x, tiles_y = grid_shape(width, height, tile)
    num_tiles = tiles_x * tiles_y
    nb = layout_blocks(gids, tile, block)
    px, py = _pixel_centres(tile_of, tiles_x, tile, means2d.dtype)
    m, con, op, f = _block_params(means2d, conics, opacities, features, gids, nb)
    pxb, pyb = _blocks(px, nb), _blocks(py, nb)
    used = _used_blocks(tile_of, nb, num_tiles)
    prod = _map_used(_local_products, (m, con, op, pxb, pyb), used, jnp.ones_like(pxb))
    carry = _seg_scan(prod.reshape(px.shape), first, jnp.multiply, 1.0)
    init = (jnp.zeros(pxb.shape + (f.shape[-1],), pxb.dtype), jnp.ones_like(pxb))
    acc, t_last = _map_used(_blend, (m, con, op, f, pxb, pyb, _blocks(carry, nb)), used, init)
    acc = acc.reshape(px.shape + (f.shape[-1],))
    t_last = t_last.reshape(px.shape)
    feat = jax.ops.segment_sum(acc, tile_of, num_segments=num_tiles + 1)[:num_tiles]
    tmin = jax.ops.segment_min(t_last, tile_of, num_segments=num_tiles + 1)[:num_tiles]
    out = (tiles_to_image(feat, width, height, tile),
           tiles_to_image(jnp.minimum(tmin, 1.0), width, height, tile))
    return out, (carry, acc)


def layout_blocks(gids, tile, block: int = BLOCK_ELEMENTS):
    """Number of blocks of the chunk array ``gids`` [NC, K] (static)."""
    per_block = max(1, block // (tile * tile))
    return gids.shape[0] // per_block


@functools.partial(jax.custom_vjp, nondiff_argnums=(7, 8, 9, 10))
def composite(means2d, conics, opacities, features, gids, tile_of, first, width, height, tile,
              block=BLOCK_ELEMENTS):
    """Blend the chunked pairs into (features float [H, W, F] = sum_i w_i f_i, transmittance
    float [H, W]).

    Args:
      means2d: float [C, 2]; conics: float [C, 3]; opacities: float [C]; features: float [C, F].
      gids, tile_of, first: the chunk layout from :func:`make_chunks`.
      width, height, tile: static sizes; block: the ``block_elements`` of the layout.
    """
    return _forward(means2d, conics, opacities, features, gids, tile_of, first, width, height,
                    tile, block)[0]


def _composite_fwd(means2d, conics, opacities, features, gids, tile_of, first, width, height, tile,
                   block):
    out, (carry, acc) = _forward(means2d, conics, opacities, features, gids, tile_of, first,
                                 width, height, tile, block)
    return out, (means2d, conics, opacities, features, gids, tile_of, first, carry, acc,
                 out[0], out[1])


def _grad_block(xs):
    """Backward on one block: per-pair gradients [K, NB, ...]."""
    m, con, op, f, px, py, carry, prefix, g_f, g_total, g_tfin = xs
    nf = f.shape[-1]
    g_ch = tuple(g_f[..., j] for j in range(nf))  # channel-major: pixel axis innermost

    def step(state, x):
        t, run = state
        mk, ck, ok, fk = x
        dx, dy, vis, raw, alpha = _alpha(mk, ck, ok, px, py)
        t_after = t * (1.0 - alpha)
        blended = t_after >= T_MIN
        w = jnp.where(blended, alpha * t, 0.0)
        s = sum(fk[:, j, None] * g_ch[j] for j in range(nf))  # g . f_i per pixel
        run = run + w * s  # g . (features up to and including this pair)
        # dC/dalpha_i = T_i f_i - (features behind i) / (1 - alpha_i); T_final likewise.
        d_alpha = t * s - (g_total - run + g_tfin) / (1.0 - alpha)
        d_raw = jnp.where(blended & (alpha > 0) & (raw < ALPHA_MAX), d_alpha, 0.0)
        d_pow = d_raw * raw
        sdx, sdy = d_pow * dx, d_pow * dy
        sums = jnp.stack([jnp.sum(v, -1) for v in (
            sdx, sdy, sdx * dx, sdx * dy, sdy * dy, d_raw * vis) + tuple(w * gj for gj in g_ch)], -1)
        a, b, c = ck[:, 0], ck[:, 1], ck[:, 2]
        d_m = -jnp.stack([a * sums[:, 0] + b * sums[:, 1], c * sums[:, 1] + b * sums[:, 0]], -1)
        d_con = jnp.stack([-0.5 * sums[:, 2], -sums[:, 3], -0.5 * sums[:, 4]], -1)
        return (t_after, run), (d_m, d_con, sums[:, 5], sums[:, 6:])

    _, grads = jax.lax.scan(step, (carry, prefix), (m, con, op, f))
    return grads


def _composite_bwd(width, height, tile, block, res, cts):
    means2d, conics, opacities, features, gids, tile_of, first, carry, acc, feat_img, trans_img = res
    g_feat, g_trans = cts
    tiles_x, _ = grid_shape(width, height, tile)
    c = means2d.shape[0]
    nb = layout_blocks(gids, tile, block)

    def per_chunk(img):
        t = image_to_tiles(img, width, height, tile)
        return jnp.concatenate([t, jnp.zeros_like(t[:1])], 0)[tile_of]

    g_f = per_chunk(g_feat)  # [NC, P, F]
    g_tfin = per_chunk(g_trans * trans_img)  # [NC, P]: dL/dT_final * T_final
    g_total = per_chunk(jnp.sum(g_feat * feat_img, -1))  # [NC, P]: g . F_total
    # g . (features of the tile's earlier chunks), per pixel.
    prefix = _seg_scan(jnp.sum(g_f * acc, -1), first, jnp.add, 0.0)

    px, py = _pixel_centres(tile_of, tiles_x, tile, means2d.dtype)
    params = _block_params(means2d, conics, opacities, features, gids, nb)
    per_pixel = tuple(_blocks(x, nb) for x in (px, py, carry, prefix, g_f, g_total, g_tfin))
    tiles_y = -(-height // tile)
    used = _used_blocks(tile_of, nb, tiles_x * tiles_y)
    init = tuple(jnp.zeros(params[0].shape[:3] + shape, means2d.dtype)
                 for shape in ((2,), (3,), (), (features.shape[-1],)))
    d_m, d_con, d_op, d_f = _map_used(_grad_block, params + per_pixel, used, init)  # [nb, K, NB, ...]

    gb = jnp.swapaxes(_blocks(gids, nb), 1, 2)
    seg = jnp.where(gb >= 0, gb, c).reshape(-1)

    def scatter(v):
        v = v.reshape((seg.shape[0],) + v.shape[3:])
        return jax.ops.segment_sum(v, seg, num_segments=c + 1)[:c]

    return (scatter(d_m), scatter(d_con), scatter(d_op), scatter(d_f), None, None, None)


composite.defvjp(_composite_fwd, _composite_bwd)


def _weigh_block(xs):
    """One block: per pair, sum over its tile's pixels of w_i(p) v(p), [K, NB, F]."""
    m, con, op, px, py, carry, vals = xs  # vals [NB, P, F]
    nf = vals.shape[-1]

    def step(t, x):
        mk, ck, ok = x
        alpha = _alpha(mk, ck, ok, px, py)[4]
        t_after = t * (1.0 - alpha)
        w = jnp.where(t_after >= T_MIN, alpha * t, 0.0)
        return t_after, jnp.stack([jnp.sum(w * vals[..., j], -1) for j in range(nf)], -1)

    _, sums = jax.lax.scan(step, carry, (m, con, op))
    return sums


def accumulate_weights(means2d, conics, opacities, values, gids, tile_of, first, width, height,
                       tile, block=BLOCK_ELEMENTS):
    """Per Gaussian, sum_p T_i(p) alpha_i(p) v(p): float [C, F] (0 for Gaussians not drawn).

    ``values``: float [H, W, F]; the other arguments as :func:`composite`'s.
    """
    tiles_x, tiles_y = grid_shape(width, height, tile)
    num_tiles = tiles_x * tiles_y
    c = means2d.shape[0]
    nb = layout_blocks(gids, tile, block)
    px, py = _pixel_centres(tile_of, tiles_x, tile, means2d.dtype)
    feats = jnp.zeros((c, 1), means2d.dtype)
    m, con, op, _ = _block_params(means2d, conics, opacities, feats, gids, nb)
    pxb, pyb = _blocks(px, nb), _blocks(py, nb)
    used = _used_blocks(tile_of, nb, num_tiles)
    prod = _map_used(_local_products, (m, con, op, pxb, pyb), used, jnp.ones_like(pxb))
    carry = _seg_scan(prod.reshape(px.shape), first, jnp.multiply, 1.0)
    t = image_to_tiles(jnp.asarray(values, means2d.dtype), width, height, tile)
    vals = jnp.concatenate([t, jnp.zeros_like(t[:1])], 0)[tile_of]  # [NC, P, F]
    nf = vals.shape[-1]
    init = jnp.zeros(m.shape[:3] + (nf,), means2d.dtype)
    sums = _map_used(_weigh_block, (m, con, op, pxb, pyb, _blocks(carry, nb), _blocks(vals, nb)),
                     used, init)  # [nb, K, NB, F]
    gb = jnp.swapaxes(_blocks(gids, nb), 1, 2)
    seg = jnp.where(gb >= 0, gb, c).reshape(-1)
    return jax.ops.segment_sum(sums.reshape(-1, nf), seg, num_segments=c + 1)[:c]
