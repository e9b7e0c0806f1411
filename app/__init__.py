"""RibPull job service: FastAPI app (app.main), job store (app.db), settings (app.settings)."""

__version__ = "0.1.0"
