"""The package's error base class (placeholder until the errors module lands)."""


class SGNJaxError(Exception):
    """Every error the package raises for bad input or a failed run derives from this."""
