"""millsense daemon: samples in, estimates, alarms and publications out."""

# The one place the version is written: pyproject.toml reads it from here (`dynamic`), so the package's
# metadata and what a running daemon reports cannot disagree, and the daemon need not parse its own
# metadata to know it (importlib.metadata's parser costs 1.5 MB of every daemon's memory).
__version__ = "0.1.0"
