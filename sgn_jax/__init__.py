"""sgn-jax: a differentiable SDF graph-network surrogate and a Hertz-Mindlin DEM for ball mills.

Importing the package enables 64-bit floats in JAX (``jax_enable_x64``): the DEM runs in
float64 by default and the surrogate's finite-difference features need float64 positions.
Every module therefore passes explicit dtypes; the surrogate casts to float32 itself. This is
the one process-wide setting the package touches, and it must happen before any array is made.
"""

import jax

jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"

__all__ = ["__version__"]
