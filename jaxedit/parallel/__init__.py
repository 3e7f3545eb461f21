"""Several devices (views sharded over a mesh) and several processes (``jax.distributed``)."""

from .views import (VIEWS, fetch, replicate, shard_local_views, shard_views, views_loss_and_grad,
                    views_loss_and_grad_jit, views_mesh, views_step, views_step_jit)

__all__ = ["VIEWS", "fetch", "replicate", "shard_local_views", "shard_views",
           "views_loss_and_grad", "views_loss_and_grad_jit", "views_mesh", "views_step",
           "views_step_jit"]
