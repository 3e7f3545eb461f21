"""The trainer of a subtask: :mod:`jaxedit.train`'s pure steps with ProEdit's density control.

:class:`EditTrainConfig` declares its knobs and makes the :class:`jaxedit.train.TrainConfig`.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from .. import densify, train
from ..train.background import background_name
from ..densify import DensifyConfig
from ..errors import DataError
from ..raster import render
from ..raster.render import next_capacity
from ..train import TrainConfig
from .plan import ProEditConfig

#: The editing trainer's density control (paper 3.3; the budget's constants are ours, the paper
#: gives only the form). ``cull_alpha`` is also the opacity a subtask start resets to, the only
#: reset; the cap is :func:`default_max_gaussians`; maintenance from the plan's W on.
EDIT_DENSIFY = DensifyConfig(max_gaussians=None, budget=True, budget_min_new=16,
                             budget_growth=0.02, budget_max_fraction=0.1, refine_every=100,
                             warmup=None, refine_from_warmup=True, stop_at=2 ** 30,
                             reset_every=0, cull_alpha=0.1)
#: IN2N / IGS2GS mode: Splatfacto's classic thresholds and its periodic opacity reset.
CLASSIC_RESET_EVERY = 3000


@dataclasses.dataclass(frozen=True)
class EditTrainConfig:
    """Optimisation settings of the editing trainer (Splatfacto learning rates, constant).

    Attributes:
      scene_extent: world size (None: ``jaxedit.train.scene_extent`` of the train cameras).
      densify: the density control as it runs (:data:`EDIT_DENSIFY`: ProEdit's budgeted
        creation; :meth:`for_mode` gives IN2N's classic one); its ``max_gaussians`` None: from
        the input (:func:`default_max_gaussians`), its ``warmup`` None: the plan's W.
      sh_degree: SH degree trained (all degrees on from the start).
      lr_means: Adam learning rate of the means (constant).
      lr_sh_dc: Adam learning rate of the SH colour (the higher SH get a twentieth).
      lr_opacity: Adam learning rate of the opacity logits.
    """

    scene_extent: float | None = None
    densify: DensifyConfig = EDIT_DENSIFY
    sh_degree: int = TrainConfig.sh_degree
    lr_means: float = TrainConfig.lr_means
    lr_sh_dc: float = TrainConfig.lr_sh_dc
    lr_opacity: float = TrainConfig.lr_opacity

    @classmethod
    def for_mode(cls, mode: str, **changes) -> "EditTrainConfig":
        """The settings of editing mode ``mode`` with ``changes``: IN2N's (in2n) classic
        density control, else ProEdit's budgeted one."""
        settings = cls(**changes)
        return settings.classic() if mode == "in2n" else settings

    def classic(self) -> "EditTrainConfig":
        """These settings with classic 3DGS density control (IN2N): no creation budget, a
        periodic opacity reset."""
        return self.replace_densify(budget=False, reset_every=CLASSIC_RESET_EVERY)

    def replace_densify(self, **changes) -> "EditTrainConfig":
        """These settings with ``densify``'s fields ``changes`` replaced."""
        return dataclasses.replace(self, densify=dataclasses.replace(self.densify, **changes))

    def train_config(self, background=ProEditConfig.background,
                     warmup: int = ProEditConfig.warmup) -> TrainConfig:
        """The :class:`jaxedit.train.TrainConfig` of these settings, on the plan's
        ``background`` (RGB, white or black) and warm-up W ``warmup`` (the density
        control's unless ``densify.warmup`` is set)."""
        dens = self.densify
        if dens.warmup is None:
            dens = dataclasses.replace(dens, warmup=int(warmup))
        return TrainConfig(iterations=2 ** 30, lr_means=self.lr_means,
                           lr_means_final=self.lr_means, lr_sh_dc=self.lr_sh_dc,
                           lr_sh_rest=self.lr_sh_dc / 20, lr_opacity=self.lr_opacity,
                           sh_degree=self.sh_degree, sh_degree_interval=1,
                           background=background_name(background), densify=dens)


#: Room the default cap leaves above a small input (Gaussians).
CAP_MIN_ROOM = 10_000


def default_max_gaussians(num_input: int) -> int:
    """The edit's default hard cap: twice the input's Gaussians, at least CAP_MIN_ROOM more
    (relative, so a large input's creation budget keeps room)."""
    return max(2 * int(num_input), int(num_input) + CAP_MIN_ROOM)


def resolve_max_gaussians(settings: EditTrainConfig, num_input: int) -> EditTrainConfig:
    """``settings`` with its cap resolved for an input of ``num_input`` Gaussians (never below)."""
    cap = settings.densify.max_gaussians
    if cap is None:
        return settings.replace_densify(max_gaussians=default_max_gaussians(num_input))
    if int(cap) < int(num_input):
        raise DataError("max_gaussians", f"{cap} is below the input scene's {num_input} "
                        "Gaussians (the cap never removes Gaussians)")
    return settings


class SubtaskTrainer:
    """An edit's view of :mod:`jaxedit.train`: the settings, init and subtask restart
    (paper 3.3 (1): opacities to the cull threshold, moments zeroed, frozen Gaussians kept,
    fresh density statistics and clock).
    """

    def __init__(self, settings: EditTrainConfig = EditTrainConfig(), num_input: int | None = None,
                 *, background=ProEditConfig.background, warmup: int = ProEditConfig.warmup,
                 editable=None):
        """``num_input``: the input's Gaussian count the cap is resolved against
        (:func:`resolve_max_gaussians`; None: the settings hold a cap); ``background``,
        ``warmup``: the plan's; ``editable``: bool [C0] over the input's slots
        (:func:`jaxedit.edit.local.editable`), the other alive Gaussians frozen (None: none)."""
        self.editable = None if editable is None else np.asarray(editable, bool)
        if num_input is not None:
            settings = resolve_max_gaussians(settings, num_input)
        elif settings.densify.max_gaussians is None:
            raise DataError("max_gaussians", "unresolved: pass num_input or a cap")
        self.settings = settings
        self.config = settings.train_config(background, warmup)

    def init(self, gaussians, cameras=None):
        """A fresh train state; with ``cameras``, its intersection buffer is sized to what
        they need (it is sorted every step, so measured rather than guessed)."""
        sh = min(self.settings.sh_degree, gaussians.sh_degree)
        config = dataclasses.replace(self.config, sh_degree=sh)
        cap = None
        if cameras is not None and len(cameras):
            needed = max(int(render(gaussians, cameras[i]).num_intersections)
                         for i in range(len(cameras)))
            cap = next_capacity(max(int(needed * 1.5), 1024))
        state = train.init_state(gaussians, config, self.settings.scene_extent,
                                 max_intersections=cap)
        if self.editable is None:
            return state
        editable = np.zeros((gaussians.capacity,), bool)
        editable[:len(self.editable)] = self.editable[:gaussians.capacity]
        return dataclasses.replace(state, frozen=jnp.asarray(np.asarray(gaussians.alive)
                                                             & ~editable))

    def restart(self, state, *, reset_opacity: bool = True):
        """``state`` at a subtask's start; ``reset_opacity`` False keeps the opacities."""
        g, opt = state.gaussians, state.opt_state
        if reset_opacity:
            g, opt = densify.opacity_reset(g, opt, state.config.densify.cull_alpha)
        if reset_opacity and state.frozen is not None:  # frozen Gaussians keep their opacity
            g = dataclasses.replace(g, opacity_logits=jnp.where(
                state.frozen, state.gaussians.opacity_logits, g.opacity_logits))
        return dataclasses.replace(state, gaussians=g, opt_state=opt,
                                   densify_stats=state.strategy.init(g), densify_origin=state.step)

    @staticmethod
    def gaussians(state):
        return state.gaussians
