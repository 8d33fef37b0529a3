"""Tests of the DAQ codec, drivers and emulator."""
