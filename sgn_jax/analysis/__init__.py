"""The analysis layer: what is computed and drawn from records.

- :mod:`sgn_jax.analysis.metrics` - docs/conventions.md section 6 metrics: a prediction against its
  DEM reference;
- :mod:`sgn_jax.analysis.collisions` - collision statistics of an event table (frequency,
  energy spectra, power above a threshold, impact speeds, normal/tangential split) and their
  ensemble means and standard errors;
- :mod:`sgn_jax.analysis.plots` - the figures (matplotlib);
- :mod:`sgn_jax.analysis.collision_plots` - the figures of the collision statistics;
- :mod:`sgn_jax.analysis.animation` - the DEM-vs-surrogate comparison GIF.

These read records (:mod:`sgn_jax.records`) and the pure rules of the core
(:mod:`sgn_jax.regime`, :mod:`sgn_jax.pairs`); the pipelines and the user layer call them. The
package ``__init__`` imports nothing, so importing the metrics does not load matplotlib
(nor do the collision statistics).
"""
