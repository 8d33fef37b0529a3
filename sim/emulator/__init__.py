"""The DAQ in software: a plant (or the test ramp) behind the real wire protocol.

``device`` holds the state a DAQ board has (index, ring, outputs, watchdog);
``wire`` turns it into frames (with injected faults for tests); ``stream_server``
and ``modbus_server`` serve it; ``runner`` and ``cli`` are `millsense sim`.
"""
