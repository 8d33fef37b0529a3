"""Tests of the reference DAQ firmware (firmware/), through its host build."""
