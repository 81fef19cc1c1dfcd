"""The service's parts made from the settings: the density model, the landability model, the
pipeline and the camera. Kept apart from the running service (``companion.service.app``) because
``companion run``, ``companion check-config``, the simulator's flights and the evaluations make
them too, each without starting a service.
"""

from __future__ import annotations

from companion import config as settings
from companion.config import Config
from companion.pipeline.density import DensityModel
from companion.pipeline.landability import LandabilityModel, LandabilityModelError, UnlandableMap
from companion.pipeline.slz import SLZPipeline
from companion.service.camera import CameraSource


def load_model(cfg: Config) -> DensityModel:
    """The density model; raises DensityModelError naming the file."""
    return DensityModel(cfg.model.path, threads=cfg.model.threads, overrides=cfg.model.overrides)


def load_landability(cfg: Config) -> UnlandableMap | None:
    """The landability model bound to ``pipeline.unlandable_levels``, or None when
    ``model.landability`` is off; raises LandabilityModelError (a DensityModelError) naming the
    file, or the key for a level the model does not have."""
    if not cfg.model.landability:
        return None
    model = LandabilityModel(cfg.model.landability_path, threads=cfg.model.threads)
    levels = cfg.pipeline.unlandable_levels or None
    try:
        return model.unlandable(levels)
    except LandabilityModelError as exc:
        raise LandabilityModelError(f"pipeline.unlandable_levels: {exc}") from None


def build_pipeline(cfg: Config, model: DensityModel, surface: UnlandableMap | None = None) -> SLZPipeline:
    """The pipeline the settings describe, for frames of ``camera.width x camera.height``;
    ``surface``: the landability model (``load_landability``), None for people alone."""
    return SLZPipeline(model, settings.pipeline_config(cfg, model.spec),
                       intrinsics=settings.intrinsics(cfg), mount=settings.mount(cfg), surface=surface)


def build_camera(cfg: Config) -> CameraSource:
    c = cfg.camera
    return CameraSource(c.source, width=c.width, height=c.height, fps=c.fps,
                        stall_timeout_s=c.stall_timeout_s, max_backoff_s=c.reopen_max_backoff_s, loop=c.loop)


__all__ = ["load_model", "load_landability", "build_pipeline", "build_camera"]
