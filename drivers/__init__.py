"""millsense drivers: bytes from a DAQ in, numbered raw samples out; commands back."""
