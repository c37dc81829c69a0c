"""ermrl: evolve reservoirs with CMA-ES in an Optuna study, learn on top of them with PPO."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("ermrl")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
