"""Application factory."""

from fastapi import FastAPI


def create_app() -> FastAPI:
    """Build the FastAPI application."""
    app = FastAPI(title="fuzzyrisk")

    @app.get("/health")
    def health() -> dict[str, str]:
        return {"status": "ok"}

    return app
