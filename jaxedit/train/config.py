"""Training settings: :class:`TrainConfig` (with :class:`jaxedit.densify.DensifyConfig`),
JSON-serialisable, stored in every checkpoint."""

from __future__ import annotations

import dataclasses

from ..densify import DensifyConfig
from ..errors import DataError, check_ranges, ranged

BACKGROUNDS = ("random", "white", "black")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Training hyper-parameters (defaults: nerfstudio Splatfacto / INRIA 3DGS).

    Attributes:
      iterations: optimiser steps of the run (one view per step).
      lr_means: means learning rate at the first step, times the scene extent (INRIA);
        decayed exponentially to ``lr_means_final`` over ``iterations`` steps.
      lr_means_final: means learning rate at the last step, times the scene extent.
      lr_sh_dc: Adam learning rate of the SH degree-0 colour.
      lr_sh_rest: Adam learning rate of the higher SH coefficients.
      lr_opacity: Adam learning rate of the opacity logits.
      lr_scales: Adam learning rate of the log-scales.
      lr_quats: Adam learning rate of the rotations (quaternions).
      adam_eps: Adam epsilon (tiny, as in 3DGS).
      lambda_dssim: loss = (1 - l) L1 + l (1 - SSIM).
      sh_degree: largest SH degree trained (<= the Gaussians').
      sh_degree_interval: steps between switching on one more SH degree, from degree 0.
      background: "random" (a uniform colour per step), "white" or "black";
        the colour behind the Gaussians in training renders.
      densify: :class:`DensifyConfig`.
      camera_opt: learn a 6-DoF pose correction per training view with the scene
        (Splatfacto's camera optimizer, gsplat's ``pose_opt``), for poses estimated by
        structure from motion (:class:`jaxedit.poses.CameraCorrections`).
      lr_camera: the pose corrections' learning rate at ``camera_opt_from`` (radians, and
        the translation in units of the view's scene depth, :func:`jaxedit.poses.apply_delta`).
      lr_camera_final: the pose corrections' learning rate at the last step (exponential
        decay from ``lr_camera``).
      camera_opt_from: the step the corrections start to move: before it the scene is
        too blurred for its photometric gradient to say where a camera points.
    """

    iterations: int = ranged(30_000, low=1)
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    adam_eps: float = 1e-15
    lambda_dssim: float = ranged(0.2, low=0.0, high=1.0)
    sh_degree: int = ranged(3, low=0, high=3)
    sh_degree_interval: int = ranged(1000, low=1)
    background: str = "white"
    densify: DensifyConfig = DensifyConfig()
    camera_opt: bool = False
    lr_camera: float = 1e-3
    lr_camera_final: float = 1e-5
    camera_opt_from: int = ranged(500, low=0)

    def __post_init__(self):
        if self.background not in BACKGROUNDS:
            raise DataError("background", f"must be one of {BACKGROUNDS}, got {self.background!r}")
        check_ranges(self)
        if not (self.lr_camera > 0 and 0 < self.lr_camera_final <= self.lr_camera):
            raise DataError("lr_camera", f"need 0 < lr_camera_final <= lr_camera, got "
                                         f"{self.lr_camera_final}, {self.lr_camera}")
        if isinstance(self.densify, dict):
            object.__setattr__(self, "densify", _densify_from_dict(self.densify))
        if self.densify.warmup is None:
            raise DataError("warmup", "is unset (None): give the steps before the first "
                                      "density maintenance")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict, where: str = "config") -> "TrainConfig":
        _check_fields(cls, data, where, "train config")
        data = dict(data)
        if "densify" in data:
            data["densify"] = _densify_from_dict(data["densify"], f"{where}.densify")
        return cls(**data)


def _densify_from_dict(data, where: str = "densify") -> DensifyConfig:
    if isinstance(data, DensifyConfig):
        return data
    _check_fields(DensifyConfig, data, where, "densify")
    return DensifyConfig(**data)


def _check_fields(cls, data, where: str, what: str) -> None:
    """DataError unless ``data`` is a dict whose keys are all fields of dataclass ``cls``."""
    if not isinstance(data, dict):
        raise DataError(where, f"{what} must be an object")
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise DataError(where, f"unknown {what} field(s) {', '.join(unknown)}")
