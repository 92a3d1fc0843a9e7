"""The web pages' templates and static assets, installed as the package `server.web` (see pyproject.toml)."""
