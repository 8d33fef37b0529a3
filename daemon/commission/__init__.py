"""`millsense commission`'s steps (docs/commissioning.md): one module a job.

- `bench.py`: the DAQ through the driver layer `run` uses, the interlock's heartbeat and hold, raw samples;
- `signals.py`: the scales against a meter, the phase order (the daemon's `PhaseCheck`), the speed source;
- `proof.py`: the feed hold (test-trip) and the DAQ's watchdog, timed;
- `report.py`: a step's result and the report the shop keeps.
"""
