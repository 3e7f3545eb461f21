"""Exact per-tile alpha compositing with a recomputing ``custom_vjp`` backward.

Shape of the computation ("chunked pair-major"). Each tile's depth-sorted list
is cut into chunks of ``K`` pairs (the last chunk of a tile padded); chunks of
all tiles are laid end to end, so there is no cap on any list and the padding
is at most K - 1 pairs per tile. For every (chunk, pair, pixel of the tile)
alpha is evaluated at once; transmittance is the product of the chunk-local
running product (exact, front to back) and the carry of the tile's earlier
chunks, obtained by a segmented exclusive scan over chunks. INRIA's stop rule
(a Gaussian that would drop T below 1e-4 is not blended, nor anything behind
it) is a prefix test on T, so it needs no loop.

The backward recomputes alpha and T instead of storing them: the residuals are
the inputs, the accumulated features and the final transmittance (memory
O(pixels + pairs)). The colour "behind" pair i, needed by dL/dalpha_i, is the
pixel's total minus the inclusive prefix sum, again via a chunk-local scan and
a segmented scan over chunks.

Static work is proportional to the buffer capacity (pairs) x 256 pixels.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from .binning import TILE, Bins, grid_shape
from .project import ALPHA_MAX, ALPHA_MIN, T_MIN

#: Pairs per chunk.
CHUNK = 32
_PIX = TILE * TILE


def num_chunks(capacity: int, num_tiles: int, chunk: int = CHUNK) -> int:
    """Static chunk count that can hold ``capacity`` pairs spread over ``num_tiles`` tiles."""
    return -(-capacity // chunk) + num_tiles


def make_chunks(bins: Bins, num_tiles: int, capacity: int, chunk: int = CHUNK):
    """Chunk layout of the sorted pairs.

    Returns:
      (gids int32 [NC, K] (-1 for padding), tile int32 [NC] (num_tiles for
      unused chunks), first bool [NC]: chunk starts its tile's list).
    """
    nc = num_chunks(capacity, num_tiles, chunk)
    start = bins.tile_start
    n_t = start[1:] - start[:-1]
    c_t = (n_t + chunk - 1) // chunk
    c_end = jnp.cumsum(c_t)
    c_begin = c_end - c_t
    j = jnp.arange(nc, dtype=jnp.int32)
    tile = jnp.searchsorted(c_end, j, side="right").astype(jnp.int32)
    used = tile < num_tiles
    t = jnp.minimum(tile, num_tiles - 1)
    first = used & (j == c_begin[t])
    idx = start[t][:, None] + (j - c_begin[t])[:, None] * chunk + jnp.arange(chunk, dtype=jnp.int32)
    ok = used[:, None] & (idx < start[t + 1][:, None])
    gids = jnp.where(ok, bins.gids[jnp.clip(idx, 0, bins.gids.shape[0] - 1)], -1)
    return gids, jnp.where(used, tile, num_tiles), first


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


def _pixel_centres(tile, tiles_x, dtype):
    """float [NC, 256] x and y pixel centres of each chunk's tile."""
    o = jnp.arange(_PIX, dtype=jnp.int32)
    tx = (tile % tiles_x) * TILE
    ty = (tile // tiles_x) * TILE
    px = (tx[:, None] + o[None] % TILE).astype(dtype) + 0.5
    py = (ty[:, None] + o[None] // TILE).astype(dtype) + 0.5
    return px, py


def _chunk_params(means2d, conics, opacities, features, gids):
    """Per-pair parameters in position-major layout [K, NC, ...] (padding: opacity 0)."""
    ok = (gids >= 0).T
    g = jnp.where(ok, gids.T, 0)
    return means2d[g], conics[g], jnp.where(ok, opacities[g], 0.0), features[g]


def _alpha(m, con, op, px, py):
    """One pair position across all chunks: dx, dy, exp(power), o exp(power), alpha [NC, 256].

    Args: m [NC, 2], con [NC, 3], op [NC], px/py [NC, 256].
    """
    dx = m[:, 0, None] - px
    dy = m[:, 1, None] - py
    power = -0.5 * (con[:, 0, None] * dx * dx + con[:, 2, None] * dy * dy) - con[:, 1, None] * dx * dy
    vis = jnp.exp(jnp.minimum(power, 0.0))
    raw = op[:, None] * vis
    alpha = jnp.minimum(ALPHA_MAX, raw)
    alpha = jnp.where((power > 0) | (alpha < ALPHA_MIN), 0.0, alpha)
    return dx, dy, vis, raw, alpha


def _local_products(params, px, py):
    """float [NC, 256]: product of (1 - alpha) over each chunk (pass 1)."""
    m, con, op, _ = params

    def step(prod, x):
        return prod * (1.0 - _alpha(*x, px, py)[4]), None

    prod, _ = jax.lax.scan(step, jnp.ones(px.shape, px.dtype), (m, con, op))
    return prod


def _blend(params, px, py, carry):
    """Pass 2: per chunk, features sum_i w_i f_i [NC, 256, F] and its last blended T [NC, 256].

    ``carry`` [NC, 256] is the transmittance in front of each chunk.
    """
    m, con, op, f = params

    def step(state, x):
        t, t_last, acc = state
        mk, ck, ok, fk = x
        alpha = _alpha(mk, ck, ok, px, py)[4]
        t_after = t * (1.0 - alpha)
        blended = t_after >= T_MIN  # a prefix of the list: T only decreases
        w = jnp.where(blended, alpha * t, 0.0)
        acc = acc + w[..., None] * fk[:, None, :]
        return (t_after, jnp.where(blended, t_after, t_last), acc), None

    init = (carry, jnp.ones_like(carry), jnp.zeros(carry.shape + (f.shape[-1],), carry.dtype))
    (_, t_last, acc), _ = jax.lax.scan(step, init, (m, con, op, f))
    return acc, t_last


def _to_image(tiles_img, width, height):
    """[num_tiles, 256, ...] tile layout -> [H, W, ...]."""
    tiles_x, tiles_y = grid_shape(width, height)
    rest = tiles_img.shape[2:]
    img = tiles_img.reshape((tiles_y, tiles_x, TILE, TILE) + rest)
    img = jnp.swapaxes(img, 1, 2).reshape((tiles_y * TILE, tiles_x * TILE) + rest)
    return img[:height, :width]


def _to_tiles(img, width, height):
    """[H, W, ...] -> [num_tiles, 256, ...] (zero-padded to whole tiles)."""
    tiles_x, tiles_y = grid_shape(width, height)
    rest = img.shape[2:]
    pad = [(0, tiles_y * TILE - height), (0, tiles_x * TILE - width)] + [(0, 0)] * len(rest)
    img = jnp.pad(img, pad).reshape((tiles_y, TILE, tiles_x, TILE) + rest)
    return jnp.swapaxes(img, 1, 2).reshape((tiles_y * tiles_x, _PIX) + rest)


def _forward(means2d, conics, opacities, features, gids, tile, first, width, height):
    tiles_x, tiles_y = grid_shape(width, height)
    num_tiles = tiles_x * tiles_y
    px, py = _pixel_centres(tile, tiles_x, means2d.dtype)
    params = _chunk_params(means2d, conics, opacities, features, gids)
    carry = _seg_scan(_local_products(params, px, py), first, jnp.multiply, 1.0)
    acc, t_last = _blend(params, px, py, carry)
    feat = jax.ops.segment_sum(acc, tile, num_segments=num_tiles + 1)[:num_tiles]
    tmin = jax.ops.segment_min(t_last, tile, num_segments=num_tiles + 1)[:num_tiles]
    out = (_to_image(feat, width, height), _to_image(jnp.minimum(tmin, 1.0), width, height))
    return out, (carry, acc)


@functools.partial(jax.custom_vjp, nondiff_argnums=(7, 8))
def composite(means2d, conics, opacities, features, gids, tile, first, width, height):
    """Blend the chunked pairs into images.

    Args:
      means2d: float [C, 2]; conics: float [C, 3]; opacities: float [C]
        (0 for culled); features: float [C, F] (colour, depth, ...).
      gids, tile, first: the chunk layout from :func:`make_chunks`.
      width, height: static image size.
    Returns:
      (features float [H, W, F] = sum_i w_i f_i, transmittance float [H, W]).
    """
    return _forward(means2d, conics, opacities, features, gids, tile, first, width, height)[0]


def _composite_fwd(means2d, conics, opacities, features, gids, tile, first, width, height):
    out, (carry, acc) = _forward(means2d, conics, opacities, features, gids, tile, first,
                                 width, height)
    return out, (means2d, conics, opacities, features, gids, tile, first, carry, acc, out[0], out[1])


def _composite_bwd(width, height, res, cts):
    means2d, conics, opacities, features, gids, tile, first, carry, acc, feat_img, trans_img = res
    g_feat, g_trans = cts
    tiles_x, _ = grid_shape(width, height)
    c = means2d.shape[0]

    def per_chunk(img):
        t = _to_tiles(img, width, height)
        return jnp.concatenate([t, jnp.zeros_like(t[:1])], 0)[tile]

    g_f = per_chunk(g_feat)  # [NC, 256, F]
    g_tfin = per_chunk(g_trans * trans_img)  # [NC, 256]: dL/dT_final * T_final
    g_total = per_chunk(jnp.sum(g_feat * feat_img, -1))  # [NC, 256]: g . F_total
    # g . (features of the tile's earlier chunks), per pixel.
    prefix = _seg_scan(jnp.sum(g_f * acc, -1), first, jnp.add, 0.0)

    px, py = _pixel_centres(tile, tiles_x, means2d.dtype)
    params = _chunk_params(means2d, conics, opacities, features, gids)

    def step(state, x):
        t, run = state
        mk, ck, ok, fk = x
        dx, dy, vis, raw, alpha = _alpha(mk, ck, ok, px, py)
        t_after = t * (1.0 - alpha)
        blended = t_after >= T_MIN
        w = jnp.where(blended, alpha * t, 0.0)
        s = jnp.einsum("nf,npf->np", fk, g_f)  # g . f_i per pixel
        run = run + w * s  # g . (features up to and including this pair)
        inv = 1.0 / (1.0 - alpha)
        d_alpha = t * s - (g_total - run + g_tfin) * inv
        d_raw = jnp.where(blended & (alpha > 0) & (raw < ALPHA_MAX), d_alpha, 0.0)
        d_pow = d_raw * raw
        a, b, cc = ck[:, 0, None], ck[:, 1, None], ck[:, 2, None]
        d_con = jnp.stack([jnp.sum(d_pow * dx * dx, -1) * -0.5, -jnp.sum(d_pow * dx * dy, -1),
                           jnp.sum(d_pow * dy * dy, -1) * -0.5], -1)
        d_m = -jnp.stack([jnp.sum(d_pow * (a * dx + b * dy), -1),
                          jnp.sum(d_pow * (cc * dy + b * dx), -1)], -1)
        d_op = jnp.sum(d_raw * vis, -1)
        d_f = jnp.einsum("np,npf->nf", w, g_f)
        return (t_after, run), (d_m, d_con, d_op, d_f)

    _, (d_m, d_con, d_op, d_f) = jax.lax.scan(step, (carry, prefix), params)
    seg = jnp.where(gids >= 0, gids, c).T.reshape(-1)

    def scatter(v):
        v = v.reshape((seg.shape[0],) + v.shape[2:])
        return jax.ops.segment_sum(v, seg, num_segments=c + 1)[:c]

    return (scatter(d_m), scatter(d_con), scatter(d_op), scatter(d_f), None, None, None)


composite.defvjp(_composite_fwd, _composite_bwd)
