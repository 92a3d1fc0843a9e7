"""Data access and rules shared by the API and the worker: pure SQLAlchemy, no FastAPI."""
