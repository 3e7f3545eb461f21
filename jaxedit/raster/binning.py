"""Tile binning: every (Gaussian, tile it touches) pair in a fixed-capacity buffer, sorted
by (tile, depth), with no per-Gaussian or per-tile cap."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .project import Projected

#: INRIA's tile size; any tile size gives the same result (tiles only group work).
TILE = 16


class Bins(NamedTuple):
    """Sorted tile intersections of one frame.

    Attributes:
      gids: int32 [N], Gaussian of each pair, sorted by (tile, depth); unused slots hold C.
      tiles: int32 [N], row-major tile of each pair; unused: num_tiles.
      tile_start: int32 [num_tiles + 1], tile t's pairs ``gids[tile_start[t]:tile_start[t+1]]``.
      num_intersections: int32 [], pairs the frame needs (may exceed N).
      overflow: bool [], num_intersections > N.
      enum_slots: int32 [N], each pair's slot in enumeration order (unused: N).
      depth_order: int32 [C], Gaussians front to back.
      run_ends: int32 [C], end of the k-th Gaussian's (depth order) run of slots.
    """

    gids: jax.Array
    tiles: jax.Array
    tile_start: jax.Array
    num_intersections: jax.Array
    overflow: jax.Array
    enum_slots: jax.Array
    depth_order: jax.Array
    run_ends: jax.Array


def grid_shape(width: int, height: int, tile: int = TILE) -> tuple[int, int]:
    """(tiles_x, tiles_y) covering a width x height image."""
    return -(-width // tile), -(-height // tile)


def tiles_to_image(tiles_img, width: int, height: int, tile: int):
    """[num_tiles, P, ...] tile layout (P = tile^2, row-major in the tile) -> [H, W, ...]."""
    tiles_x, tiles_y = grid_shape(width, height, tile)
    rest = tiles_img.shape[2:]
    img = tiles_img.reshape((tiles_y, tiles_x, tile, tile) + rest)
    img = jnp.swapaxes(img, 1, 2).reshape((tiles_y * tile, tiles_x * tile) + rest)
    return img[:height, :width]


def image_to_tiles(img, width: int, height: int, tile: int):
    """[H, W, ...] -> [num_tiles, P, ...] tile layout (zero-padded to whole tiles)."""
    tiles_x, tiles_y = grid_shape(width, height, tile)
    rest = img.shape[2:]
    pad = [(0, tiles_y * tile - height), (0, tiles_x * tile - width)] + [(0, 0)] * len(rest)
    img = jnp.pad(img, pad).reshape((tiles_y, tile, tiles_x, tile) + rest)
    return jnp.swapaxes(img, 1, 2).reshape((tiles_y * tiles_x, tile * tile) + rest)


def tile_rects(proj: Projected, width: int, height: int, tile: int = TILE):
    """Tile rectangle of each Gaussian's footprint: (x0, y0, nx, ny) int32 [C], the
    first tile column/row and the count covered (0 for invisible)."""
    tiles_x, tiles_y = grid_shape(width, height, tile)
    m = jax.lax.stop_gradient(proj.means2d)
    ext = proj.extents
    # Pixel columns whose centre (x + 0.5) lies in [mx - ex, mx + ex], clipped to the image.
    px0 = jnp.clip(jnp.ceil(m[:, 0] - ext[:, 0] - 0.5), 0, width - 1)
    px1 = jnp.clip(jnp.floor(m[:, 0] + ext[:, 0] - 0.5), 0, width - 1)
    py0 = jnp.clip(jnp.ceil(m[:, 1] - ext[:, 1] - 0.5), 0, height - 1)
    py1 = jnp.clip(jnp.floor(m[:, 1] + ext[:, 1] - 0.5), 0, height - 1)
    x0 = (px0 // tile).astype(jnp.int32)
    x1 = (px1 // tile).astype(jnp.int32)
    y0 = (py0 // tile).astype(jnp.int32)
    y1 = (py1 // tile).astype(jnp.int32)
    vis = proj.visible
    nx = jnp.where(vis, jnp.clip(x1 - x0 + 1, 0, tiles_x), 0)
    ny = jnp.where(vis, jnp.clip(y1 - y0 + 1, 0, tiles_y), 0)
    return x0, y0, nx, ny


def count_intersections(proj: Projected, width: int, height: int, tile: int = TILE) -> jax.Array:
    """int32 scalar: tile intersections the frame needs."""
    _, _, nx, ny = tile_rects(proj, width, height, tile)
    return jnp.sum(nx * ny)


def _pair_owners(counts, capacity: int):
    """int32 [capacity]: for each slot, the Gaussian k whose run of ``counts[k]`` slots holds
    it (past the total: the last with pairs), by a running maximum (no ``searchsorted``)."""
    c = counts.shape[0]
    starts = jnp.cumsum(counts) - counts
    marks = jnp.zeros(capacity, jnp.int32).at[jnp.where(counts > 0, starts, capacity)].max(
        jnp.arange(c, dtype=jnp.int32), mode="drop")
    return jax.lax.cummax(marks)


def bin_gaussians(proj: Projected, width: int, height: int, capacity: int,
                  tile: int = TILE) -> Bins:
    """Sorted (tile, depth) intersections in a buffer of static ``capacity``, depth ties by
    Gaussian index as in the oracle."""
    tiles_x, tiles_y = grid_shape(width, height, tile)
    num_tiles = tiles_x * tiles_y
    c = proj.means2d.shape[0]
    depth = jnp.where(proj.visible, jax.lax.stop_gradient(proj.depths), jnp.inf)
    order = jnp.argsort(depth, stable=True).astype(jnp.int32)  # front to back
    x0, y0, nx, ny = (a[order] for a in tile_rects(proj, width, height, tile))
    counts = nx * ny
    ends = jnp.cumsum(counts)  # int32: fine below 2^31 pairs
    total = ends[-1] if c else jnp.zeros((), jnp.int32)
    slots = jnp.arange(capacity, dtype=jnp.int32)
    rank = _pair_owners(counts, capacity)
    local = slots - (ends[rank] - counts[rank])  # k-th tile of the owner's rectangle
    w = jnp.maximum(nx[rank], 1)
    tile_id = jnp.where(slots < total, (y0[rank] + local // w) * tiles_x + x0[rank] + local % w,
                        num_tiles)  # unused slots: num_tiles, so they sort last
    if num_tiles * c + c < 2**31:
        key_sorted = jax.lax.sort(tile_id * c + rank)
        tiles_sorted, rank_sorted = key_sorted // c, key_sorted % c
        # The pair's position in enumeration order, recovered from (tile, rank).
        tx, ty = tiles_sorted % tiles_x, tiles_sorted // tiles_x
        enum_slot = (ends[rank_sorted] - counts[rank_sorted]
                     + (ty - y0[rank_sorted]) * nx[rank_sorted] + tx - x0[rank_sorted])
    else:
        enum_slot = jnp.argsort(tile_id.astype(jnp.uint32), stable=True).astype(jnp.int32)
        tiles_sorted, rank_sorted = tile_id[enum_slot], rank[enum_slot]
    tile_start = jnp.searchsorted(tiles_sorted, jnp.arange(num_tiles + 1, dtype=jnp.int32),
                                  side="left").astype(jnp.int32)
    in_use = tiles_sorted < num_tiles
    gids = jnp.where(in_use, order[rank_sorted], c).astype(jnp.int32)
    return Bins(gids=gids, tiles=jnp.where(in_use, tiles_sorted, num_tiles).astype(jnp.int32),
                tile_start=tile_start, num_intersections=total.astype(jnp.int32),
                overflow=total > capacity,
                enum_slots=jnp.where(in_use, enum_slot, capacity).astype(jnp.int32),
                depth_order=order, run_ends=ends.astype(jnp.int32))
