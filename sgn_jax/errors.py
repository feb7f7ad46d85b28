"""The package's one error base class.

Every error that sgn-jax raises for bad input or for a run that failed (a config key, a damaged
checkpoint, a DEM that left the jar, a diverged rollout, ...) derives from :class:`SGNJaxError`,
so a script can catch them all with one ``except`` and the CLI prints them as one line (exit 2).
Each module keeps its own subclass (``ConfigError``, ``DEMError``, ``CheckpointError``, ...), which
also derives from the matching builtin (``ValueError`` or ``RuntimeError``).

Warnings derive from :class:`SGNJaxWarning`, which is both an :class:`SGNJaxError` and a
``UserWarning``: ``warnings.warn(msg, EnvelopeWarning)`` works as for any warning, ``-W error`` turns it
into an exception that the same ``except SGNJaxError`` catches, and
``warnings.simplefilter("ignore", SGNJaxWarning)`` silences all of the package's warnings.
"""


class SGNJaxError(Exception):
    """Every error the package raises for bad input or a failed run derives from this."""


class SGNJaxWarning(SGNJaxError, UserWarning):
    """Every warning the package issues derives from this (and so from :class:`SGNJaxError`)."""


class EnvelopeWarning(SGNJaxWarning):
    """A design or run lies outside what the model or the DEM was validated for (it still runs)."""


__all__ = ["EnvelopeWarning", "SGNJaxError", "SGNJaxWarning"]
