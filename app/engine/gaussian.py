"""Constants of the Gaussian error model behind every reported accuracy radius.

The API's ``accuracy`` is the radius of the circle holding the position with
68 % probability. For an isotropic 2-D Gaussian of per-axis σ the squared
distance over σ² is χ² with two degrees of freedom, whose quantile function is
``χ²₂⁻¹(p) = −2 ln(1 − p)``; the radius is the square root of that times σ.
"""

from __future__ import annotations

import numpy as np

R68_SIGMAS_2D = float(np.sqrt(-2.0 * np.log(1.0 - 0.68)))
"""Radius, in σ of an isotropic 2-D Gaussian, of the circle holding 68 % of it (≈ 1.51)."""
