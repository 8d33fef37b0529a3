"""millsense daemon: samples in, estimates, alarms and publications out."""
