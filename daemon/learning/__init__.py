"""Learned limits per process (issue 14): context, envelopes, tool wear, the operator's actions.

Pure logic like `daemon/pipeline/alarms.py`: no I/O, no threads, no clock. The
runner feeds it revolution by revolution and persists what it reports changed;
replay runs the same code on a capture. See docs/learning.md.

- `context.py`: which context (program, tool, operation, flags) holds at a sample.
- `envelope.py`: the learned statistics and band of one process key.
- `wear.py`: tool life and wear per tool number.
- `process.py`: one process being watched (its per-revolution arrays, its alarms).
- `keys.py`: the state of one process key (learning, pending, active) and its summaries.
- `actions.py`: the operator's actions (accept, relearn, widen, narrow, false_alarm, new_tool, low_off, low_on).
- `monitor.py`: `ProcessMonitor`, which ties them together.
"""
