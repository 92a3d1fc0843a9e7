"""Alembic's migrations of the server's database, installed as the package `server.migrations` (see pyproject.toml)."""
