"""The HTTP front: ``factory.create_app(settings)`` builds the FastAPI app; handlers stay thin.

Routes (``routes/``) parse and answer, and call ``app.service.MapService``; the middleware checks the API
key and bounds bodies before a route runs; ``errors`` answers every error with the one ``ErrorBody``.
"""

__all__ = ["auth", "deps", "errors", "factory", "httpserver", "largebody", "middleware", "routes"]
