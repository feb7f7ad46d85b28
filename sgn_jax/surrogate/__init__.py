"""The surrogate (pure JAX core): featurizer, model kinds, normalisation, training, rollout.

- :mod:`sgn_jax.surrogate.graph` - the one featurizer: windows -> padded graphs;
- :mod:`sgn_jax.surrogate.normalization` - the normalisation statistics;
- :mod:`sgn_jax.surrogate.model` - the model registry (``[model] kind``), the contract every kind
  honours, the layers the kinds share and ``make_predict``;
- the model kinds, one file each, side by side: :mod:`sgn_jax.surrogate.sgn` (the paper's SDF
  graph network, kind "sgn") and :mod:`sgn_jax.surrogate.contact` (the contact-impulse model,
  kind "contact", with its unrolled-loss training in :mod:`sgn_jax.surrogate.contact_train`)
  and :mod:`sgn_jax.surrogate.contact_charge` (the same model conditioned on each contact's
  radii, masses and material, kind "contact_charge");
- :mod:`sgn_jax.surrogate.train` - loss, packed batches, the training and evaluation steps;
- :mod:`sgn_jax.surrogate.rollout` - the surrogate as an init/step pair and a scan;
- :mod:`sgn_jax.surrogate.collisions` - the contact model's collision ledger, recorded in the
  rollout's scan.

Importing the package registers the built-in model kinds (the imports below), so whatever
imports a surrogate module finds them in the registry. A new kind is one file beside
``sgn.py`` that calls :func:`sgn_jax.surrogate.model.register_model` at import, plus its import
here (docs/sgn.md, "Adding a surrogate model").
"""

from sgn_jax.surrogate import contact, contact_charge, sgn  # noqa: F401  (register the kinds)
