"""Evaluation server: REST API, leaderboard and admin around the PDMS engine (FastAPI, SQLAlchemy 2)."""
