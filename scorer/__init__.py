"""PDM Score engine for NAVSIM v1.0 and v1.1: a pure library (numpy, shapely 2, scipy)."""

ENGINE_VERSION = "0.3.0"
