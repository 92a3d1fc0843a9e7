"""The PDM Score's metrics, one module each, over arrays of proposals x time (spec 6-8)."""
