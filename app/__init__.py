"""ElastoID: identify the Young's modulus of each tissue region from a robotic indentation."""

__version__ = "0.1.0"
