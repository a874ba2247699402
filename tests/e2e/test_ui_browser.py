"""The operator page in a real browser (Debian's Chromium driven by Playwright) against a real server.

A server process (``conftest.Server``) is started with a fresh data directory, the e2e
world's hall is scanned into a map through the API, and the page is used as an operator
would: choose the map, click a start and a goal, press Plan.
Set UPDATE_SCREENSHOT=1 to refresh docs/img/ui.png.
"""

from __future__ import annotations

import os
import re
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
import numpy as np
import pytest
from playwright.sync_api import Browser, Page, expect

from app.formats.exports import RISK_LUT, UNKNOWN_RGB
from planning import available_planners
from tests.e2e.conftest import BEAMS, PATIENCE_S, POSES, ROOT, WORLD_MAP, Server, laser_json

pytestmark = pytest.mark.slow

API_KEY = "operator-key-0123456789abcdef"

# The e2e world's hall (10 m x 6 m, a middle wall at x = 4.9 .. 5.1 with a door at y = 2.4 .. 3.6),
# mapped with a 0.5 m margin all round so that the page has never-observed cells to show.
ORIGIN = (-0.5, -0.5)
SIZE = (11.0, 7.0)
RES = WORLD_MAP["resolution"]
WIDTH, HEIGHT = round(SIZE[0] / RES), round(SIZE[1] / RES)
START, GOAL, GOAL_IN_WALL = (2.51, 1.51), (7.51, 1.51), (5.0, 1.0)


def create_hall_map(client: httpx.Client, name: str) -> None:
    """Create the map and fuse the hall's scans in one batch."""
    response = client.post("/maps", json={**WORLD_MAP, "name": name, "origin": list(ORIGIN), "size": list(SIZE)})
    assert response.status_code == 201, response.text
    response = client.post(f"/maps/{name}/scans", json={"scans": [laser_json(p) for p in POSES]})
    assert response.status_code == 200, response.text


def api_client(server: Server, key: str | None = None) -> httpx.Client:
    headers = {"Authorization": f"Bearer {key}"} if key else {}
    return httpx.Client(base_url=server.url, headers=headers, timeout=60.0)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    srv = Server(tmp_path_factory.mktemp("ui") / "data", env={"FUZZYRISK_PLAN_WARMUP": "true"})  # ready to plan
    try:
        srv.start()
        with api_client(srv) as client:
            create_hall_map(client, "hall")
        yield srv
    finally:
        srv.stop()


def open_map(page: Page, url: str, name: str) -> None:
    page.goto(url + "/")
    page.get_by_role("button", name=f"Show map {name}").click()
    expect(page.locator("#map-canvas")).to_have_attribute("data-version", re.compile(r"^\d+$"))


def cell_centre(x: float, y: float) -> tuple[float, float]:
    """World centre of the cell holding (x, y): origin + (index + 0.5) * resolution."""
    i, j = np.floor((np.array([x, y]) - ORIGIN) / RES)
    return ORIGIN[0] + (i + 0.5) * RES, ORIGIN[1] + (j + 0.5) * RES


def click_world(page: Page, x: float, y: float) -> None:
    """Click the middle of the cell holding (x, y) as drawn (PNG: one pixel per cell, top row = highest y)."""
    box = page.locator("#map-canvas").bounding_box()
    assert box is not None
    cx, cy = cell_centre(x, y)
    u = (cx - ORIGIN[0]) / RES / WIDTH
    v = 1.0 - (cy - ORIGIN[1]) / RES / HEIGHT
    page.mouse.click(box["x"] + u * box["width"], box["y"] + v * box["height"])


def canvas_rgb(page: Page, x: float, y: float) -> list[int]:
    """The colour the canvas shows at the world point (x, y)."""
    u = (x - ORIGIN[0]) / RES / WIDTH
    v = 1.0 - (y - ORIGIN[1]) / RES / HEIGHT
    return page.evaluate("""([u, v]) => {
        const c = document.getElementById('map-canvas');
        const px = c.getContext('2d').getImageData(Math.floor(u * c.width), Math.floor(v * c.height), 1, 1).data;
        return Array.from(px.slice(0, 3));
    }""", [u, v])


def path_coloured_pixels(page: Page) -> int:
    """Canvas pixels in the path's colour (magenta), which no risk colour and no overlay uses."""
    return page.evaluate("""() => {
        const c = document.getElementById('map-canvas');
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let n = 0;
        for (let i = 0; i < d.length; i += 4) if (d[i] > 230 && d[i + 1] < 40 && d[i + 2] > 230) n++;
        return n;
    }""")


def test_page_is_served_and_lists_the_maps(server: Server, page: Page) -> None:
    assert httpx.get(server.url + "/").headers["location"].endswith("ui/")
    page.goto(server.url + "/")
    assert page.url == server.url + "/ui/"
    row = page.locator('#maps-body tr[data-name="hall"]')
    expect(row).to_contain_text("11 × 7 m")
    expect(row).to_contain_text(f"{WIDTH} × {HEIGHT} @ 0.05 m")
    expect(row).to_contain_text("fuzzy")
    info = httpx.get(server.url + "/maps/hall").json()
    cells = row.locator("td")
    expect(cells.nth(3)).to_have_text(str(info["scans_fused"]))
    expect(cells.nth(4)).to_have_text(str(info["version"]))
    offered = page.locator("#planner option").evaluate_all("options => options.map(o => o.value)")
    assert offered == list(available_planners())
    # every control has a name a screen reader can read out
    unnamed = page.evaluate("""() => [...document.querySelectorAll('input, select, button')]
        .filter(el => !(el.labels && el.labels.length) && !el.getAttribute('aria-label') && !el.textContent.trim())
        .map(el => el.id || el.outerHTML)""")
    assert unnamed == []


def test_legend_shows_the_colours_of_the_service_png(server: Server, page: Page) -> None:
    page.goto(server.url + "/ui/")
    bar = page.evaluate("""() => {
        const c = document.getElementById('legend-bar');
        const d = c.getContext('2d').getImageData(0, 0, c.width, 1).data;
        return {width: c.width, rgb: Array.from(d)};
    }""")
    for risk in (0.0, 0.25, 0.5, 0.75, 1.0):
        x = round(risk * (bar["width"] - 1))
        shown = np.array(bar["rgb"][4 * x: 4 * x + 3])
        served = RISK_LUT[round(risk * 255)].astype(int)
        assert np.abs(shown - served).max() <= 3, (risk, shown, served)
    swatch = page.locator("#unknown-swatch").evaluate("el => getComputedStyle(el).backgroundColor")
    assert swatch == "rgb({}, {}, {})".format(*UNKNOWN_RGB)


def test_risk_image_is_drawn_and_reloaded_only_when_the_map_changes(server: Server, page: Page) -> None:
    png_requests: list[str] = []
    page.on("request", lambda r: png_requests.append(r.url) if "/risk" in r.url else None)
    open_map(page, server.url, "hall")
    version = httpx.get(server.url + "/maps/hall").json()["version"]
    canvas = page.locator("#map-canvas")
    expect(canvas).to_have_attribute("data-version", str(version))
    expect(canvas).to_have_attribute("aria-label", re.compile(r"Risk map of hall"))
    page.get_by_label("Show the last scan's beams").uncheck()
    # never-observed cells outside the hall and free cells inside it must not look alike
    assert canvas_rgb(page, -0.3, 6.3) == list(UNKNOWN_RGB)
    assert canvas_rgb(page, 2.5, 4.0) != list(UNKNOWN_RGB)
    # the page polls the map list every second but fetches the PNG again only for a new version: two polls
    # that began after this count have run to their end (the PNG fetched or not) once a third one asks
    loads = len(png_requests)
    for _ in range(3):
        with page.expect_request(lambda r: r.method == "GET" and urlsplit(r.url).path == "/maps",
                                 timeout=PATIENCE_S * 1000):
            pass
    assert len(png_requests) == loads
    with api_client(server) as client:
        # the batch's last scan again, so that the hall looks the same to the tests after this one
        new_version = client.post("/maps/hall/scans", json={"scans": [laser_json(POSES[-1])]})
    assert new_version.status_code == 200
    expect(canvas).to_have_attribute("data-version", str(new_version.json()["version"]))
    assert len(png_requests) == loads + 1
    expect(page.locator('#maps-body tr[data-name="hall"] td').nth(4)).to_have_text(
        str(new_version.json()["version"])
    )


def test_last_scan_beams_are_shown(server: Server, page: Page) -> None:
    scan = laser_json((2.0, 3.0, 0.3))
    scan["ranges"][::4] = ["inf"] * len(scan["ranges"][::4])  # dropouts: they clear through walls, a map of its own
    returns = sum(r != "inf" for r in scan["ranges"])
    with api_client(server) as client:
        create_hall_map(client, "dropouts")
        assert client.post("/maps/dropouts/scans", json={"scans": [scan]}).status_code == 200
    open_map(page, server.url, "dropouts")
    expect(page.locator("#scan-text")).to_have_text(
        f"Last scan: {BEAMS} beams, {returns} returns, {BEAMS - returns} without return, "
        "sensor at (2.000, 3.000)."
    )
    # the beams are drawn: hiding them changes the canvas
    with_beams = page.locator("#map-canvas").screenshot()
    page.get_by_label("Show the last scan's beams").uncheck()
    assert page.locator("#map-canvas").screenshot() != with_beams


def test_clicked_start_and_goal_give_a_drawn_path(server: Server, page: Page, tmp_path: Path) -> None:
    open_map(page, server.url, "hall")
    assert path_coloured_pixels(page) == 0
    click_world(page, *START)
    click_world(page, *GOAL)
    # each click set the centre of the cell under it, start first, then goal
    typed = [float(page.locator(f"#{field}").input_value()) for field in ("start-x", "start-y", "goal-x", "goal-y")]
    assert typed == pytest.approx([*cell_centre(*START), *cell_centre(*GOAL)], abs=1e-9)
    page.get_by_label("Planner").select_option("grid")
    page.get_by_role("button", name="Plan").click()
    result = page.locator("#plan-result")
    expect(result).not_to_have_attribute("data-state", "busy")
    assert result.get_attribute("data-state") == "path", result.inner_text()
    expect(result).to_contain_text(re.compile(r"length \d+\.\d\d m, max risk 0\.\d\d"))
    assert int(result.get_attribute("data-path-points") or 0) > 1
    # the middle wall is in the way: the path goes round by the door, longer than the straight line
    length = float(re.search(r"length (\d+\.\d+) m", result.inner_text()).group(1))
    assert length > np.hypot(GOAL[0] - START[0], GOAL[1] - START[1]) + 0.5
    assert path_coloured_pixels(page) > 50
    shot = tmp_path / "ui.png"
    page.screenshot(path=str(shot), full_page=True)
    if os.environ.get("UPDATE_SCREENSHOT") == "1":
        (ROOT / "docs" / "img").mkdir(parents=True, exist_ok=True)
        shutil.copyfile(shot, ROOT / "docs" / "img" / "ui.png")


def test_typed_goal_inside_a_wall_is_refused_in_words(server: Server, page: Page) -> None:
    open_map(page, server.url, "hall")
    # a keyboard user: type the coordinates and press Enter
    for field, value in [("#start-x", START[0]), ("#start-y", START[1]), ("#goal-x", GOAL_IN_WALL[0]),
                         ("#goal-y", GOAL_IN_WALL[1])]:
        page.focus(field)
        page.keyboard.type(str(value))
    page.keyboard.press("Enter")
    result = page.locator("#plan-result")
    expect(result).not_to_have_attribute("data-state", "busy")
    assert result.get_attribute("data-state") == "error", result.inner_text()
    expect(result).to_contain_text("GOAL_OCCUPIED")
    expect(result).to_contain_text("The goal is in an obstacle or too close to one")
    assert result.get_attribute("data-path-points") == "0"
    assert path_coloured_pixels(page) == 0


def test_3d_map_is_shown_as_its_projection_with_z_fields(server: Server, page: Page) -> None:
    with api_client(server) as client:
        created = client.post("/maps", json={
            "name": "hall3d", "dimensions": 3, "resolution": 0.1, "origin": [0.0, 0.0, 0.0], "size": [3.0, 2.0, 1.0],
        })
        assert created.status_code == 201, created.text
        # a wall 1.5 m ahead of a sensor at (0.5, 1.0, 0.5) looking along +x
        ys, zs = np.meshgrid(np.linspace(-0.8, 0.8, 17), np.linspace(-0.4, 0.4, 9))
        points = np.stack([np.full(ys.size, 1.5), ys.ravel(), zs.ravel()], axis=1)
        cloud = {"pose": {"position": [0.5, 1.0, 0.5], "orientation": [0.0, 0.0, 0.0, 1.0]},
                 "points": points.tolist(), "range_max": 5.0}
        assert client.post("/maps/hall3d/scans", json={"scans": [cloud]}).status_code == 200
    open_map(page, server.url, "hall3d")
    expect(page.locator("#map-summary")).to_contain_text("3-D map, shown as its maximum risk over z")
    expect(page.locator("#map-summary")).to_contain_text("30 × 20 cells shown")
    expect(page.locator("#start-z")).to_be_visible()
    expect(page.locator("#scan-text")).to_contain_text(f"{len(points)} beams, {len(points)} returns")
    # the wall's column at x = 2.0 m is drawn in a risk colour, the never-seen corner in unknown's colour
    wall, corner = page.evaluate("""() => {
        const c = document.getElementById('map-canvas');
        const g = c.getContext('2d');
        const at = (u, v) => Array.from(g.getImageData(Math.floor(u * c.width), Math.floor(v * c.height), 1, 1).data);
        document.getElementById('show-scan').click();
        return [at(2.05 / 3, 0.5), at(0.98, 0.02)];
    }""")
    assert corner[:3] == list(UNKNOWN_RGB)
    wall_risk = np.abs(RISK_LUT.astype(int) - wall[:3]).sum(axis=1).argmin() / 255
    assert wall_risk > 0.6


def test_page_asks_for_the_api_key_once_and_then_works(tmp_path: Path, browser: Browser) -> None:
    srv = Server(tmp_path / "data", env={"FUZZYRISK_API_KEY": API_KEY})
    try:
        srv.start()
        with api_client(srv, API_KEY) as client:
            create_hall_map(client, "secure")
        # the page's own files need no key; the API does
        assert httpx.get(srv.url + "/ui/app.js").status_code == 200
        assert httpx.get(srv.url + "/maps").status_code == 401
        context = browser.new_context()
        page = context.new_page()
        page.goto(srv.url + "/ui/")
        key_field = page.get_by_role("textbox", name="API key")
        expect(key_field).to_be_visible()
        expect(key_field).to_be_focused()
        key_field.fill("not-the-key-not-the-key")
        key_field.press("Enter")
        expect(page.locator("#auth-msg")).to_contain_text("rejected")
        expect(page.locator("#maps-body tr")).to_have_count(0)
        key_field.fill(API_KEY)
        page.get_by_role("button", name="Use key").click()
        expect(page.locator("#auth")).to_be_hidden()
        open_map_row = page.get_by_role("button", name="Show map secure")
        expect(open_map_row).to_be_visible()
        open_map_row.click()
        expect(page.locator("#map-canvas")).to_have_attribute("data-version", re.compile(r"^\d+$"))
        # kept for the tab: a reload does not ask again
        page.reload()
        expect(page.get_by_role("button", name="Show map secure")).to_be_visible()
        assert page.locator("#auth").is_hidden()
        context.close()
    finally:
        srv.stop()


def test_the_api_docs_render_with_no_network_beyond_the_service(server: Server, page: Page) -> None:
    """An offline robot's network: anything not served by the service itself is refused."""
    outside: list[tuple[str, str]] = []

    def only_the_service(route: Any) -> None:
        if route.request.url.startswith(server.url):
            route.continue_()
        else:
            outside.append((route.request.resource_type, route.request.url))
            route.abort()

    page.route("**/*", only_the_service)
    page.goto(server.url + "/docs")
    expect(page.locator(".opblock-summary-path", has_text="/maps/{name}/plan")).to_be_visible()
    assert outside == []
    page.goto(server.url + "/redoc")
    expect(page.get_by_role("heading", name="fuzzyrisk (0.1.0)")).to_be_visible()
    expect(page.get_by_text("Post Scans").first).to_be_attached()
    # ReDoc's footer links its maker's logo from their CDN: cosmetic, the only thing allowed to miss
    assert [kind for kind, _ in outside] in ([], ["image"]), outside


def test_a_growing_map_is_drawn_within_its_bounds_and_follows_them(server: Server, page: Page) -> None:
    with api_client(server) as client:
        made = client.post("/maps", json={"name": "roam", "resolution": RES})
        assert made.status_code == 201, made.text
        page.goto(server.url + "/")
        row = page.locator('#maps-body tr[data-name="roam"] td').first
        expect(row).to_have_text("growing, nothing observed yet (2-D)")
        page.get_by_role("button", name="Show map roam").click()
        expect(page.locator("#map-summary")).to_have_text(re.compile("nothing observed yet"))
        for poses, label in ((POSES[:1], "first"), (POSES, "all")):
            fused = client.post("/maps/roam/scans", json={"scans": [laser_json(p) for p in poses]})
            assert fused.status_code == 200, fused.text
            info = client.get("/maps/roam").json()
            expect(page.locator("#map-canvas")).to_have_attribute("data-version", str(info["version"]),
                                                                 timeout=PATIENCE_S * 1000)
            width, height = info["shape"]
            # the image is the map's bounds, one pixel a cell, and the page says where they are
            expect(page.locator("#map-summary")).to_contain_text(f"({width} × {height} cells shown)")
            expect(row).to_contain_text("growing")
            if label == "first":
                first_shape = (width, height)
        assert (width, height) != first_shape  # the bounds grew with the scans, and the page followed
    page.get_by_label("Show the last scan's beams").uncheck()

    def rgb(x: float, y: float) -> list[int]:  # the canvas at a world point, the image placed at the bounds
        u = (x - info["origin"][0]) / RES / width
        v = 1.0 - (y - info["origin"][1]) / RES / height
        return page.evaluate("""([u, v]) => {
            const c = document.getElementById('map-canvas');
            return Array.from(c.getContext('2d').getImageData(Math.floor(u * c.width), Math.floor(v * c.height), 1, 1)
                .data.slice(0, 3));
        }""", [u, v])

    wall, free = rgb(4.92, 1.0), rgb(2.5, 3.0)  # the face of the hall's middle wall, and the floor before it
    assert wall != list(UNKNOWN_RGB) and free != list(UNKNOWN_RGB)
    assert wall[1] < free[1]  # crimson where the wall is, pale where the floor is
