"""Emulate a GPU's TF32 matrix units on the CPU, to find where float32 precision matters.

On NVIDIA GPUs since Ampere, XLA runs a float32 ``dot_general`` / convolution
whose precision is left at ``DEFAULT`` on the tensor cores in TF32: each operand
is rounded to a 10-bit mantissa (relative error up to 2^-11, about 5e-4) and
the products are accumulated in float32. The CPU computes the same ops in full
float32, so a model can train on the CPU and fail on a GPU.

:func:`emulate_tf32` rewrites a function's jaxpr so that every such op rounds
its float32 operands to TF32 first (round to nearest even, as cuBLAS converts),
while ops asking for ``Precision.HIGHEST`` (or an explicit algorithm) stay
exact. Wrapped around a *differentiated* function it covers the backward dots
too (JAX's transpose rules keep the forward op's precision). It is a
diagnostic for the tests (``tests/test_backbone.py``); the library never calls it, so it
lives here, not in the package.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.extend import core as jcore

#: Primitives whose DEFAULT precision means TF32 on an NVIDIA GPU.
_MATRIX_PRIMS = ("dot_general", "conv_general_dilated")
#: Call-like primitives inlined by the interpreter (their custom rules are not needed:
#: the emulated function is evaluated, never differentiated again).
_INLINE = ("pjit", "jit", "closed_call", "core_call", "custom_jvp_call", "custom_vjp_call",
           "custom_vjp_call_jaxpr", "remat", "checkpoint", "custom_lin")


def round_tf32(x: jax.Array) -> jax.Array:
    """float32 array rounded to TF32 (10 explicit mantissa bits, round to nearest even).

    Other dtypes are returned unchanged. Infinities and NaNs are kept.
    """
    if x.dtype != jnp.float32:
        return x
    bits = jax.lax.bitcast_convert_type(x, jnp.uint32)
    lsb = (bits >> 13) & 1
    rounded = (bits + jnp.uint32(0xFFF) + lsb) & jnp.uint32(0xFFFFE000)
    return jnp.where(jnp.isfinite(x), jax.lax.bitcast_convert_type(rounded, jnp.float32), x)


def _is_default_precision(precision) -> bool:
    """True when an op's ``precision`` parameter lets a GPU use TF32."""
    if precision is None:
        return True
    if isinstance(precision, tuple):
        return all(_is_default_precision(p) for p in precision)
    return precision == jax.lax.Precision.DEFAULT


def _closed(jaxpr) -> jcore.ClosedJaxpr:
    return jaxpr if isinstance(jaxpr, jcore.ClosedJaxpr) else jcore.ClosedJaxpr(jaxpr, ())


def _transform_closed(closed: jcore.ClosedJaxpr, counter: dict) -> jcore.ClosedJaxpr:
    """The emulated version of a closed jaxpr (same signature)."""
    avals = [jax.ShapeDtypeStruct(v.aval.shape, v.aval.dtype) for v in closed.jaxpr.invars]
    return jax.make_jaxpr(lambda *a: _eval(closed.jaxpr, closed.consts, a, counter))(*avals)


def _eval(jaxpr, consts, args, counter: dict):
    env = {}

    def read(v):
        return v.val if isinstance(v, jcore.Literal) else env[v]

    for v, c in zip(jaxpr.constvars, consts):
        env[v] = c
    for v, a in zip(jaxpr.invars, args):
        env[v] = a
    for eqn in jaxpr.eqns:
        invals = [read(v) for v in eqn.invars]
        name = eqn.primitive.name
        params = dict(eqn.params)
        if name in _MATRIX_PRIMS and _is_default_precision(params.get("precision")):
            counter[name] = counter.get(name, 0) + 1
            invals = [round_tf32(x) for x in invals]
            outs = eqn.primitive.bind(*invals, **params)
        elif name in _INLINE:
            sub = params.get("jaxpr", params.get("call_jaxpr", params.get("fun_jaxpr")))
            sub = _closed(sub)
            outs = _eval(sub.jaxpr, sub.consts, invals, counter)
        else:
            for k, v in params.items():
                if isinstance(v, (jcore.ClosedJaxpr, jcore.Jaxpr)):
                    params[k] = _transform_closed(_closed(v), counter)
                    if isinstance(v, jcore.Jaxpr):
                        params[k] = params[k].jaxpr
                elif isinstance(v, tuple) and v and all(isinstance(b, jcore.ClosedJaxpr) for b in v):
                    params[k] = tuple(_transform_closed(b, counter) for b in v)
            outs = eqn.primitive.bind(*invals, **params)
        if not eqn.primitive.multiple_results:
            outs = [outs]
        for v, o in zip(eqn.outvars, outs):
            env[v] = o
    return [read(v) for v in jaxpr.outvars]


def emulate_tf32(fn, *, counter: dict | None = None):
    """``fn`` with every DEFAULT-precision float32 dot/conv computed on TF32-rounded operands.

    Args:
      fn: a JAX-traceable function of arrays / pytrees.
      counter: optional dict; receives the number of rounded ops per primitive
        (counted when the emulated function is traced).
    Returns:
      a function with ``fn``'s signature and output pytree (not jitted: wrap it).
    """
    counter = {} if counter is None else counter

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        closed, out_shape = jax.make_jaxpr(functools.partial(fn, **kwargs), return_shape=True)(*args)
        flat = jax.tree_util.tree_leaves(args)
        outs = _eval(closed.jaxpr, closed.consts, flat, counter)
        return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(out_shape), outs)

    return wrapped
