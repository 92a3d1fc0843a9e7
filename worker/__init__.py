"""Celery workers that score submissions: `worker.app` (configuration), `worker.tasks`, `worker.cli`."""
