"""The toolkit version (one place; the package and its reports read it from here)."""

__version__ = "0.1.0"
