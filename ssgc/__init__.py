"""ssgc: the spatial scene grammar compiler."""

__version__ = "0.1.0"
