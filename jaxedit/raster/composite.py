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


def _gather(means2d, conics, opacities, gids):
    ok = gids >= 0
    g = jnp.where(ok, gids, 0)
    return means2d[g], conics[g], jnp.where(ok, opacities[g], 0.0)


def _alpha_terms(m, con, op, px, py):
    """Per (chunk, pair, pixel): dx, dy, vis = exp(power), raw = o vis, alpha."""
    dx = m[:, :, None, 0] - px[:, None, :]
    dy = m[:, :, None, 1] - py[:, None, :]
    a, b, c = con[:, :, None, 0], con[:, :, None, 1], con[:, :, None, 2]
    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    vis = jnp.exp(jnp.minimum(power, 0.0))
    raw = op[:, :, None] * vis
    alpha = jnp.minimum(ALPHA_MAX, raw)
    alpha = jnp.where((power > 0) | (alpha < ALPHA_MIN), 0.0, alpha)
    return dx, dy, vis, raw, alpha


def _transmittance(alpha, first):
    """T before/after each pair: float [NC, K, 256] each, and the blended mask."""
    one_minus = 1.0 - alpha
    local_after = jnp.cumprod(one_minus, axis=1)
    local_before = jnp.concatenate([jnp.ones_like(local_after[:, :1]), local_after[:, :-1]], 1)
    carry = _seg_scan(local_after[:, -1], first, jnp.multiply, 1.0)  # [NC, 256]
    t_before = carry[:, None] * local_before
    t_after = carry[:, None] * local_after
    return t_before, t_after, t_after >= T_MIN


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
    dtype = means2d.dtype
    px, py = _pixel_centres(tile, tiles_x, dtype)
    m, con, op = _gather(means2d, conics, opacities, gids)
    f = features[jnp.where(gids >= 0, gids, 0)]
    _, _, _, _, alpha = _alpha_terms(m, con, op, px, py)
    t_before, t_after, blended = _transmittance(alpha, first)
    w = jnp.where(blended, alpha * t_before, 0.0)
    chunk_feat = jnp.einsum("nkp,nkf->npf", w, f)
    chunk_tmin = jnp.min(jnp.where(blended, t_after, 1.0), axis=1)
    feat = jax.ops.segment_sum(chunk_feat, tile, num_segments=num_tiles + 1)[:num_tiles]
    tmin = jax.ops.segment_min(chunk_tmin, tile, num_segments=num_tiles + 1)[:num_tiles]
    trans = jnp.minimum(tmin, 1.0)
    return _to_image(feat, width, height), _to_image(trans, width, height)


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
    return _forward(means2d, conics, opacities, features, gids, tile, first, width, height)


def _composite_fwd(means2d, conics, opacities, features, gids, tile, first, width, height):
    out = _forward(means2d, conics, opacities, features, gids, tile, first, width, height)
    return out, (means2d, conics, opacities, features, gids, tile, first, out[0], out[1])


def _composite_bwd(width, height, res, cts):
    means2d, conics, opacities, features, gids, tile, first, feat_img, trans_img = res
    g_feat, g_trans = cts
    tiles_x, tiles_y = grid_shape(width, height)
    num_tiles = tiles_x * tiles_y
    dtype = means2d.dtype
    c = means2d.shape[0]

    # Per-pixel quantities in tile layout, one extra zero tile for unused chunks.
    def per_chunk(img):
        t = _to_tiles(img, width, height)
        t = jnp.concatenate([t, jnp.zeros_like(t[:1])], 0)
        return t[tile]

    g_f = per_chunk(g_feat)  # [NC, 256, F]
    g_t = per_chunk(g_trans)  # [NC, 256]
    t_fin = per_chunk(trans_img)  # [NC, 256]
    g_total = per_chunk(jnp.sum(g_feat * feat_img, -1))  # [NC, 256]: g . F_total

    px, py = _pixel_centres(tile, tiles_x, dtype)
    m, con, op = _gather(means2d, conics, opacities, gids)
    safe = jnp.where(gids >= 0, gids, 0)
    f = features[safe]
    dx, dy, vis, raw, alpha = _alpha_terms(m, con, op, px, py)
    t_before, _, blended = _transmittance(alpha, first)
    w = jnp.where(blended, alpha * t_before, 0.0)

    s = jnp.einsum("nkf,npf->nkp", f, g_f)  # g . f_i per pixel
    ws = w * s
    local = jnp.cumsum(ws, axis=1)
    prefix = _seg_scan(local[:, -1], first, jnp.add, 0.0)  # [NC, 256]
    incl = prefix[:, None] + local
    inv = 1.0 / (1.0 - alpha)
    d_alpha = t_before * s - (g_total[:, None] - incl) * inv - (g_t * t_fin)[:, None] * inv
    d_alpha = jnp.where(blended & (alpha > 0) & (raw < ALPHA_MAX), d_alpha, 0.0)

    d_feat = jnp.einsum("nkp,npf->nkf", w, g_f)
    d_op = jnp.sum(d_alpha * vis, -1)
    d_pow = d_alpha * raw
    a, b, cc = con[:, :, None, 0], con[:, :, None, 1], con[:, :, None, 2]
    d_a = jnp.sum(d_pow * (-0.5) * dx * dx, -1)
    d_b = jnp.sum(d_pow * (-dx * dy), -1)
    d_c = jnp.sum(d_pow * (-0.5) * dy * dy, -1)
    d_mx = jnp.sum(d_pow * -(a * dx + b * dy), -1)
    d_my = jnp.sum(d_pow * -(cc * dy + b * dx), -1)

    seg = jnp.where(gids >= 0, gids, c).reshape(-1)

    def scatter(v):
        v = v.reshape((seg.shape[0],) + v.shape[2:])
        return jax.ops.segment_sum(v, seg, num_segments=c + 1)[:c]

    d_means = scatter(jnp.stack([d_mx, d_my], -1))
    d_conics = scatter(jnp.stack([d_a, d_b, d_c], -1))
    return (d_means, d_conics, scatter(d_op), scatter(d_feat), None, None, None)


composite.defvjp(_composite_fwd, _composite_bwd)
