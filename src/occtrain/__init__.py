"""occtrain: multi-stage training for occupancy-language-action driving world models."""

__version__ = "0.1.0"
