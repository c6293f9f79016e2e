"""Base layer: errors, angles, the machine's facts, files, configuration files, progress, provenance, signals."""
