"""The pipeline layer: where a config meets the pure JAX core, and where the host drivers live.

The core (``sgn_jax.motion``, ``sgn_jax.geometry``, ``sgn_jax.dem`` engine and contact laws,
the surrogate ``sgn_jax.surrogate``: featurizer, model kinds, normalisation, rollout, training
step and loss; ``sgn_jax.design``) never imports ``sgn_jax.config`` or file I/O
(``tests/test_architecture.py`` checks the import graph). Everything that reads a config or
touches files is here:

- :mod:`sgn_jax.pipelines.configure` - every ``*_from_config`` adapter (config -> core spec,
  params, motion, jar geometry, SDF grid), and the STL / SDF-grid file cache;
- :mod:`sgn_jax.pipelines.features` - dataset trajectory -> graph windows and training samples
  (the frequency feature from the same motion object the rollout uses);
- :mod:`sgn_jax.pipelines.dem_run` - the resumable, chunked DEM driver (``sgn-jax dem``);
- :mod:`sgn_jax.pipelines.train_run` - the training loop (``sgn-jax train``);
- :mod:`sgn_jax.pipelines.rollout_run` - checkpoint + dataset -> prediction file
  (``sgn-jax rollout``);
- :mod:`sgn_jax.pipelines.validation` - the checks at the boundary before any work starts
  (durations, fill, contact resolution of a motion, the DEM's validated range, a model's motion
  envelope);
- :mod:`sgn_jax.pipelines.demo` - ``sgn-jax demo`` and the shipped models;
- :mod:`sgn_jax.pipelines.experiments` - what the experiment scripts share (starting the CLI on
  pinned cores, its JSON summary line, a model's evaluation on an ensemble).
"""
