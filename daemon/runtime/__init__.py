"""The live daemon, built only by `millsense run`: the Runner's threads and the parts it builds (docs/architecture.md)."""
