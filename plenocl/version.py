"""The package's version, importable by any module without the package root."""

__version__ = "0.1.0"
