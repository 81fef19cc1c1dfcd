"""A density model that records the frames the pipeline gives it (shared by the pipeline's tests
of what the model is shown: the fisheye's crop, the shrunk frame)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from companion.pipeline.density import DensityModel, DensitySpec


@dataclass
class Recorded:
    """The shipped model, and the shapes of the frames it was given (the model's own spec and
    size rule, so the pipeline crops and shrinks for it as for the model itself)."""

    model: DensityModel
    shapes: list[tuple[int, ...]] = field(default_factory=list)

    @property
    def spec(self) -> DensitySpec:
        return self.model.spec

    @property
    def any_size(self) -> bool:
        return self.model.any_size

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        self.shapes.append(frame.shape)
        return self.model(frame)
