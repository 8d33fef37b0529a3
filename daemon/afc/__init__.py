"""Adaptive feed control (docs/afc.md): the pure controller, the override output, and the supervisor that runs them live."""
