"""Data: episode records and references, their formats and importers, generated cycles, metrics, windows, datasets."""
