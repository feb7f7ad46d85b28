"""The records layer: the files the package reads and writes, checked at the edge.

- :mod:`sgn_jax.records.base` - what the ``.npz`` record files share (array specs, meta,
  validated atomic write and read);
- :mod:`sgn_jax.records.trajectory` - the DEM trajectory file (docs/conventions.md section 4);
- :mod:`sgn_jax.records.prediction` - the rollout prediction file;
- :mod:`sgn_jax.records.checkpoint` - orbax checkpoints of a trained surrogate, with digests,
  and the shipped models;
- :mod:`sgn_jax.records.io_utils` - atomic writes, JSON, content hashes;
- :mod:`sgn_jax.records.cache` - the user cache (compilation cache, settled packings);
- :mod:`sgn_jax.records.ensembles` - the ensembles file of the experiments;
- :mod:`sgn_jax.records.envelope` - the shipped model's motion envelope and designs over it.

Records sit above the core (they build and check core objects) and below the pipelines; the
package ``__init__`` imports nothing, so ``sgn_jax.config`` can use ``io_utils`` without a cycle
(docs/architecture.md, "Layers").
"""
