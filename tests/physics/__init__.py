"""Tests of millsense.daemon.physics (pure functions, no I/O)."""
