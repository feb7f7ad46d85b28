"""Hertz-Mindlin DEM in JAX (SPEC sections 3-4): contact law, engine, placement, driver."""

from sgn_jax.dem.contact import (
    ContactLaw,
    contact_forces,
    damping_factor_from_restitution,
    hertz_contact_time,
    make_contact_law,
)
from sgn_jax.dem.engine import (
    DISSIPATION_KINDS,
    DEMError,
    DEMParams,
    DEMSpec,
    DEMState,
    EnergyLedger,
    energies,
    init_state,
    ledger_balance,
    make_advance,
    make_dem_step,
    make_params,
    make_sampler,
    observe,
)
from sgn_jax.dem.walls import PlaneWalls, plane_wall_fn, plane_walls

__all__ = [
    "DISSIPATION_KINDS",
    "ContactLaw",
    "DEMError",
    "DEMParams",
    "DEMSpec",
    "DEMState",
    "EnergyLedger",
    "PlaneWalls",
    "contact_forces",
    "damping_factor_from_restitution",
    "energies",
    "hertz_contact_time",
    "init_state",
    "ledger_balance",
    "make_advance",
    "make_contact_law",
    "make_dem_step",
    "make_params",
    "make_sampler",
    "observe",
    "plane_wall_fn",
    "plane_walls",
]
