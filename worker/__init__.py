"""RibPull Celery worker: `celery -A worker.celery_app worker` runs `worker.tasks.run_job`."""
