"""The PDM Score's metrics, one module each, over arrays of proposals x time (docs/engine.md, "Metrics")."""
