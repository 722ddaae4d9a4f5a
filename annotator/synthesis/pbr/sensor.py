"""The camera sensor of the physically based render: exposure, shot and read noise, 8 bits.

A machine-vision camera is linear (no tone curve): the rendered radiance is scaled by the
exposure, turned into electrons (``full_well`` of them fill a pixel), drawn with Poisson
shot noise plus Gaussian read noise, and quantised.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SensorSettings:
    """Exposure and noise.

    Attributes:
        exposure: Stops above the automatic exposure, which puts the image's
            ``auto_percentile`` percentile at ``auto_level`` of full scale.
        full_well: Electrons at full scale (fewer: more shot noise).
        read_noise: Read noise, electrons (Gaussian).
        noise: False: no noise at all (an ideal sensor).
    """

    exposure: float = 0.0
    auto_percentile: float = 99.0
    auto_level: float = 0.9
    full_well: float = 6000.0
    read_noise: float = 6.0
    noise: bool = True


def grey(rgb: np.ndarray) -> np.ndarray:
    """Linear luminance (Rec. 709) of a linear RGB image (H, W, 3)."""
    return (rgb[..., 0] * 0.2126 + rgb[..., 1] * 0.7152 + rgb[..., 2] * 0.0722).astype(np.float32)


def exposure_scale(radiance: np.ndarray, settings: SensorSettings) -> float:
    """The factor that takes ``radiance`` to full-scale fractions under ``settings``."""
    level = float(np.percentile(radiance, settings.auto_percentile))
    return settings.auto_level / max(level, 1e-6) * 2.0**settings.exposure


def expose(
    radiance: np.ndarray, settings: SensorSettings, *, scale: float, rng: np.random.Generator
) -> np.ndarray:
    """The uint8 image the sensor reads of ``radiance`` (linear, any units) times ``scale``.

    >>> import numpy as np
    >>> img = expose(np.full((2, 2), 0.5), SensorSettings(noise=False), scale=1.0,
    ...              rng=np.random.default_rng(0))
    >>> img.tolist()
    [[128, 128], [128, 128]]
    """
    signal = np.clip(radiance * scale, 0.0, None)
    if settings.noise:
        electrons = rng.poisson(signal * settings.full_well).astype(np.float64)
        electrons += rng.normal(0.0, settings.read_noise, signal.shape)
        signal = electrons / settings.full_well
    return np.clip(np.round(signal * 255.0), 0, 255).astype(np.uint8)
