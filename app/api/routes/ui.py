"""The operator web page: `GET /` redirects to `/ui/`, and `/ui/...` serves `app/api/static/`.

Files are served by explicit routes over a fixed list (a router cannot mount
`StaticFiles`), which also rules out path traversal. The page's own files need
no API key: the page asks for the key itself when an API call answers 401.
"""

from pathlib import Path

from fastapi import APIRouter, HTTPException
from fastapi.responses import FileResponse, RedirectResponse

STATIC_DIR = Path(__file__).resolve().parent.parent / "static"

# name -> media type; nothing outside this list is ever served
_FILES: dict[str, str] = {
    "index.html": "text/html; charset=utf-8",
    "app.js": "text/javascript; charset=utf-8",
    "style.css": "text/css; charset=utf-8",
}
# small files, and an operator who upgrades the service should get the new page on reload
_HEADERS = {"Cache-Control": "no-cache"}

router = APIRouter(include_in_schema=False)


@router.api_route("/", methods=["GET", "HEAD"])
def root() -> RedirectResponse:
    """Send a browser that opens the service's address to the page."""
    return RedirectResponse(url="ui/", status_code=307)


@router.api_route("/ui", methods=["GET", "HEAD"])
def ui_no_slash() -> RedirectResponse:
    """Redirect to `/ui/` so that the page's relative URLs resolve under it."""
    return RedirectResponse(url="ui/", status_code=307)


@router.api_route("/ui/", methods=["GET", "HEAD"])
def ui_index() -> FileResponse:
    """The page itself."""
    return ui_file("index.html")


@router.api_route("/ui/{name}", methods=["GET", "HEAD"])
def ui_file(name: str) -> FileResponse:
    """One of the page's files; 404 for any other name."""
    media_type = _FILES.get(name)
    if media_type is None:
        raise HTTPException(status_code=404, detail=f"no such file in the web page: {name!r}")
    return FileResponse(STATIC_DIR / name, media_type=media_type, headers=_HEADERS)
