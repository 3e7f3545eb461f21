"""Several devices and several processes.

* :mod:`.views` -- data parallelism over a mesh of devices: views sharded, the scene
  replicated (:func:`views_step`, :func:`shard_views`, :func:`replicate`, ...);
* :mod:`.distributed` -- a run over several processes (``jax.distributed``): its
  :class:`~jaxedit.parallel.distributed.DistributedConfig`, joining the runtime, the
  supervision of each worker, and the editor split over the processes.
"""

from .views import (VIEWS, fetch, replicate, shard_local_views, shard_views, views_loss_and_grad,
                    views_loss_and_grad_jit, views_mesh, views_step, views_step_jit)

__all__ = ["VIEWS", "fetch", "replicate", "shard_local_views", "shard_views",
           "views_loss_and_grad", "views_loss_and_grad_jit", "views_mesh", "views_step",
           "views_step_jit"]
