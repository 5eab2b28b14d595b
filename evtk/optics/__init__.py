"""Geometry and light transport of the two-DMD shadow-casting bench.

Coordinates and conventions
---------------------------
The laser lights the kernel DMD; a relay images the kernel onto a diffuser,
which turns every lit kernel element into an incoherent source. The feature
DMD sits ``z_mm`` after the diffuser and the screen ``u_mm`` after the feature
DMD. A source at position ``s`` in the diffuser plane lights screen point ``X``
through feature-DMD point ``m = s*u/(u+z) + X*z/(u+z)``. Two consequences:

* the feature mask lands on the screen magnified by ``M = (u+z)/z``
  (:func:`shadow_magnification`);
* displacing the source by ``s`` moves the shadow across the mask by
  ``s/sigma`` with ``sigma = (u+z)/u`` (eq. 3): a feature element of pitch
  ``F_pt`` corresponds to an extent ``sigma*F_pt`` in the diffuser plane, which is
  the "effective extent" of eq. 2, and the kernel element that matches it is
  ``varsigma*K_pt`` with ``varsigma`` from eq. 4.

Screen point ``X`` therefore sees ``sum_j K_j F(X/(M F_pt) + offset_j)``: the
shadows of sources at increasing positions sample the mask at increasing
positions. The device computes a **cross-correlation** (``out[i] = sum_j K[j]
F[i+j]``, scipy's ``correlate2d``), the same form as the paper's discretised
response with a light-transport matrix. If the relay between kernel DMD and
diffuser inverts the image (a single imaging lens does), the kernel reaches the
diffuser flipped and the device computes a true convolution
(``convolve2d``); :attr:`Bench.kernel_flipped` selects this.

Response units: :func:`screen_response` returns, per sensor pixel, the light
it collects in units of "one fully lit kernel element seen through one open
feature element", averaged over the pixel's footprint. In the ideal case
(matched scaling, stride 1, point sources, no blur) it equals the digital
correlation of kernel and features exactly.
"""

from __future__ import annotations

from .bench import Bench, load_bench, save_bench
from .geometry import (
    PHOTON_ENERGY_J_PER_NM,
    effective_extents_um,
    effective_stride,
    min_capture_window_us,
    optical_scaling,
    shadow_magnification,
    software_scaling,
    stride_mm,
)
from .screen import (
    axis_weights,  # noqa: F401  (the reconstruction's deblurring model)
    brightest_response,
    glow_response,
    ideal_response,
    response_origin_px,
    response_region,
    response_to_sensor_grid,
    screen_response,
)

__all__ = [
    "Bench", "effective_extents_um", "optical_scaling", "software_scaling", "stride_mm", "effective_stride",
    "min_capture_window_us", "shadow_magnification", "screen_response", "ideal_response", "glow_response",
    "brightest_response", "response_region", "response_origin_px", "response_to_sensor_grid", "load_bench",
    "save_bench", "PHOTON_ENERGY_J_PER_NM",
]
