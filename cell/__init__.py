"""cell: a networked industrial robot cell on one machine (README.md)."""

__version__ = "0.1.0"
