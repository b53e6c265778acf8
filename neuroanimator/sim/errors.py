"""The errors of models and simulation, importable without MuJoCo."""

from __future__ import annotations


class ModelError(ValueError):
    """A model that cannot be built or used as asked; the message names the problem."""
