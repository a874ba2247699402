"""The operator page's motion models (SE2, Dubins, Reeds-Shepp) in a real browser against a real server.

Same set-up as ``test_ui_browser.py``: a server process with a fresh data directory, the e2e
world's hall scanned into a 2-D map (and a small 3-D map), Debian's Chromium driven by
Playwright. What is checked is what an operator relies on: the motion models offered fit the
map, heading and turning-radius fields appear when they apply, the request carries what was
typed, bad input is refused in words before anything is sent, a seed repeats a plan, and the
start and goal markers point where their heading says.
Set UI_DUBINS_SCREENSHOT=/some/file.png to keep a screenshot of the page with a Dubins path.
"""

from __future__ import annotations

import math
import os
import re
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from playwright.sync_api import Page, Request, Route, expect

from tests.e2e.conftest import POSES, WORLD_MAP, Server, laser_json

pytestmark = pytest.mark.slow


# The hall (see test_ui_browser.py) with a 0.5 m margin; start and goal on either side of the
# middle wall, so every path goes through the door at y = 2.4 .. 3.6.
ORIGIN = (-0.5, -0.5)
SIZE = (11.0, 7.0)
RES = WORLD_MAP["resolution"]
WIDTH, HEIGHT = round(SIZE[0] / RES), round(SIZE[1] / RES)
START, GOAL = (2.525, 1.525), (7.525, 1.525)
PLANAR = ["R2", "SE2", "Dubins", "ReedsShepp"]
LABELS = ["R2 (x, y)", "SE2 (x, y, heading)", "Dubins car (forward only)", "Reeds-Shepp car (forward, reverse)"]
# a stand-in answer for tests that look only at what the page sends (no planner run)
FAKE_RESULT = {"status": "exact", "path": [[*START, 0.0], [*GOAL, 0.0]], "length": 5.0, "max_risk": 0.1,
               "mean_risk": 0.05, "cost": 5.2, "planner": "RRTstar", "state_space": "SE2",
               "planning_time": 0.01, "message": "", "version": 1}


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    srv = Server(tmp_path_factory.mktemp("ui-motion") / "data", env={"FUZZYRISK_PLAN_WARMUP": "true"})  # ready to plan
    try:
        srv.start()
        with httpx.Client(base_url=srv.url, timeout=60.0) as client:
            created = client.post("/maps", json={**WORLD_MAP, "name": "hall", "origin": list(ORIGIN),
                                                 "size": list(SIZE)})
            assert created.status_code == 201, created.text
            fused = client.post("/maps/hall/scans", json={"scans": [laser_json(p) for p in POSES]})
            assert fused.status_code == 200, fused.text
            created = client.post("/maps", json={"name": "cube", "dimensions": 3, "resolution": 0.1,
                                                 "origin": [0.0, 0.0, 0.0], "size": [2.0, 2.0, 1.0]})
            assert created.status_code == 201, created.text
        yield srv
    finally:
        srv.stop()


def open_map(page: Page, url: str, name: str) -> None:
    page.goto(url + "/ui/")
    page.get_by_role("button", name=f"Show map {name}").click()
    expect(page.locator("#map-canvas")).to_have_attribute("data-version", re.compile(r"^\d+$"))
    # the motion models come from GET /planners, asked after the first poll of the map list
    expect(page.locator("#planner option")).not_to_have_count(1)


def offered_models(page: Page) -> list[tuple[str, str]]:
    pairs = page.locator("#motion-model option").evaluate_all("os => os.map(o => [o.value, o.textContent])")
    return [(value, text) for value, text in pairs]


def type_poses(page: Page, start: tuple[float, ...], goal: tuple[float, ...]) -> None:
    """Type (x, y[, heading]) for start and goal as a keyboard user would."""
    for which, pose in (("start", start), ("goal", goal)):
        for axis, value in zip(("x", "y", "theta"), pose, strict=False):
            page.locator(f"#{which}-{axis}").fill(str(value))


def plan_and_wait(page: Page) -> dict[str, Any]:
    """Press Plan; the JSON body the page sent. Waits for the answer to be shown."""
    with page.expect_request(lambda r: r.method == "POST" and r.url.endswith("/maps/hall/plan")) as sent:
        page.get_by_role("button", name="Plan").click()
    result = page.locator("#plan-result")
    expect(result).not_to_have_attribute("data-state", "busy")
    body = sent.value.post_data_json
    assert isinstance(body, dict)
    return body


def path_coloured_pixels(page: Page) -> int:
    return page.evaluate("""() => {
        const c = document.getElementById('map-canvas');
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let n = 0;
        for (let i = 0; i < d.length; i += 4) if (d[i] > 230 && d[i + 1] < 40 && d[i + 2] > 230) n++;
        return n;
    }""")


def dark_around(page: Page, x: float, y: float, dx_px: float, dy_px: float) -> bool:
    """Whether the canvas is near-black (the heading arrow) at an offset in canvas pixels from the world point."""
    return page.evaluate("""([u, v, dx, dy]) => {
        const c = document.getElementById('map-canvas');
        const g = c.getContext('2d');
        const px = Math.round(u * c.width + dx), py = Math.round(v * c.height + dy);
        const d = g.getImageData(px - 1, py - 1, 3, 3).data;
        for (let i = 0; i < d.length; i += 4) if (d[i] < 60 && d[i + 1] < 60 && d[i + 2] < 60) return true;
        return false;
    }""", [(x - ORIGIN[0]) / RES / WIDTH, 1.0 - (y - ORIGIN[1]) / RES / HEIGHT, dx_px, dy_px])


def test_motion_models_fit_the_map(server: Server, page: Page) -> None:
    served = httpx.get(server.url + "/planners").json()["state_spaces"]
    open_map(page, server.url, "hall")
    select = page.get_by_label("Motion model")
    assert offered_models(page) == [(v, t) for v, t in zip(PLANAR, LABELS, strict=True) if v in served]
    expect(select).to_have_value("R2")
    # R2: positions only, nothing new to fill in
    expect(page.locator("#start-theta")).to_be_hidden()
    expect(page.locator("#goal-theta")).to_be_hidden()
    expect(page.get_by_label("Turning radius (m)")).to_be_hidden()
    expect(page.get_by_label("Seed (optional)")).to_be_visible()
    # SE2: headings, no turning radius
    select.select_option("SE2")
    expect(page.locator("#start-theta")).to_be_visible()
    expect(page.locator("#start-theta")).to_have_value("0")
    expect(page.locator("#goal-theta")).to_have_value("0")
    expect(page.locator("#heading-hint")).to_contain_text("radians")
    expect(page.get_by_label("Turning radius (m)")).to_be_hidden()
    # Dubins: both, and the hint says what the model is
    select.select_option("Dubins")
    expect(page.locator("#goal-theta")).to_be_visible()
    expect(page.get_by_label("Turning radius (m)")).to_be_visible()
    expect(page.get_by_label("Turning radius (m)")).to_have_value("0.5")
    expect(page.locator("#motion-hint")).to_contain_text("forward only")
    # the new controls are named, and the heading fields say their unit
    unnamed = page.evaluate("""() => [...document.querySelectorAll('input, select, button')]
        .filter(el => !(el.labels && el.labels.length) && !el.getAttribute('aria-label') && !el.textContent.trim())
        .map(el => el.id || el.outerHTML)""")
    assert unnamed == []
    assert page.locator("#start-theta").evaluate("el => el.labels[0].textContent") == "heading (rad)"
    # a 3-D map plans in R3 only, without headings
    page.get_by_role("button", name="Show map cube").click()
    assert offered_models(page) == [("R3", "R3 (x, y, z)")]
    expect(select).to_have_value("R3")
    expect(page.locator("#start-z")).to_be_visible()
    expect(page.locator("#start-theta")).to_be_hidden()
    expect(page.get_by_label("Turning radius (m)")).to_be_hidden()
    # back on a 2-D map: the planar models again
    page.get_by_role("button", name="Show map hall").click()
    assert [v for v, _ in offered_models(page)] == [v for v in PLANAR if v in served]


def test_typed_dubins_plan_sends_headings_and_turning_radius(server: Server, page: Page, tmp_path: Path) -> None:
    open_map(page, server.url, "hall")
    page.get_by_label("Show the last scan's beams").uncheck()
    page.get_by_label("Motion model").select_option("Dubins")
    type_poses(page, (*START, 0), (*GOAL, 1.5708))
    page.get_by_label("Turning radius (m)").fill("0.4")
    page.get_by_label("Time limit (s)").fill("4")
    body = plan_and_wait(page)
    assert body["state_space"] == "Dubins"
    assert body["turning_radius"] == 0.4
    assert body["start"] == [*START, 0]
    assert body["goal"] == [*GOAL, 1.5708]
    assert "seed" not in body  # empty seed field: not sent
    result = page.locator("#plan-result")
    assert result.get_attribute("data-state") == "path", result.inner_text()
    expect(result).to_contain_text(re.compile(r"planned by RRTstar in Dubins in \d+\.\d{3} s"))
    assert int(result.get_attribute("data-path-points") or 0) > 10
    assert path_coloured_pixels(page) > 50
    # the waypoints list names each heading; the path leaves and arrives as asked
    page.get_by_text("Path waypoints").click()  # open the list, as an operator would
    items = page.locator("#path-list li")
    expect(items.first).to_have_text("(2.525, 1.525), heading 0.000 rad")
    # the last pose is within the goal tolerance (one cell, in the Dubins metric) of the goal
    last = re.fullmatch(r"\((-?[\d.]+), (-?[\d.]+)\), heading (-?[\d.]+) rad", items.last.inner_text())
    assert last is not None, items.last.inner_text()
    x, y, heading = (float(v) for v in last.groups())
    assert [x, y] == pytest.approx(list(GOAL), abs=0.06)
    # the goal tolerance is one cell of Dubins distance: a heading off by up to a cell / turning radius
    assert heading == pytest.approx(1.5708, abs=RES / 0.4 + 0.001)
    expect(page.locator("#map-canvas")).to_have_attribute("aria-label", re.compile(
        r"start \(2\.525, 1\.525\), heading 0\.000 rad; goal \(7\.525, 1\.525\), heading 1\.571 rad; a path of"))
    shot = tmp_path / "ui_dubins.png"
    page.screenshot(path=str(shot), full_page=True)
    if os.environ.get("UI_DUBINS_SCREENSHOT"):
        shutil.copyfile(shot, os.environ["UI_DUBINS_SCREENSHOT"])


def test_bad_turning_radius_heading_or_seed_is_refused_in_words_without_a_request(server: Server, page: Page) -> None:
    sent: list[Request] = []
    page.on("request", lambda r: sent.append(r) if r.url.endswith("/plan") else None)
    open_map(page, server.url, "hall")
    page.get_by_label("Motion model").select_option("ReedsShepp")
    type_poses(page, (*START, 0), (*GOAL, 0))
    result = page.locator("#plan-result")
    radius = page.get_by_label("Turning radius (m)")
    for bad in ("0", "-0.5", ""):
        radius.fill(bad)
        page.get_by_role("button", name="Plan").click()
        expect(result).to_have_attribute("data-state", "error")
        expect(result).to_have_text("Turning radius must be a number greater than 0 (metres).")
        # the field is marked and focused, so a keyboard user can fix it at once
        expect(radius).to_have_attribute("aria-invalid", "true")
        expect(radius).to_be_focused()
    radius.fill("0.5")
    expect(radius).not_to_have_attribute("aria-invalid", "true")
    seed = page.get_by_label("Seed (optional)")
    for bad in ("-1", "1.5", "4294967296", "seven", "1e3"):
        seed.fill(bad)
        seed.press("Enter")  # Enter in a field submits, as for the other fields
        expect(result).to_have_text("Seed must be a whole number from 0 to 4294967295, or empty for a random plan.")
        expect(seed).to_have_attribute("aria-invalid", "true")
    seed.fill("")
    page.locator("#goal-theta").fill("")
    page.get_by_role("button", name="Plan").click()
    expect(result).to_have_text("Goal heading must be a number (radians).")
    page.wait_for_timeout(300)
    assert sent == [], [r.url for r in sent]


def test_requests_carry_what_applies_and_r2_is_unchanged(server: Server, page: Page) -> None:
    bodies: list[dict[str, Any]] = []

    def answer(route: Route) -> None:
        bodies.append(route.request.post_data_json)
        route.fulfill(status=200, json={**FAKE_RESULT, "state_space": bodies[-1]["state_space"]})

    page.route("**/maps/hall/plan", answer)
    open_map(page, server.url, "hall")
    type_poses(page, START, GOAL)
    page.get_by_role("button", name="Plan").click()
    expect(page.locator("#plan-result")).to_have_attribute("data-state", "path")
    # R2 as before: two numbers a point, no heading, turning radius or seed
    assert bodies[-1]["state_space"] == "R2"
    assert bodies[-1]["start"] == list(START) and bodies[-1]["goal"] == list(GOAL)
    assert not {"turning_radius", "seed"} & bodies[-1].keys()
    # SE2 with the largest seed: headings and seed, but no turning radius
    page.get_by_label("Motion model").select_option("SE2")
    page.locator("#start-theta").fill("-3.1416")
    page.get_by_label("Seed (optional)").fill("4294967295")
    page.get_by_role("button", name="Plan").click()
    expect(page.locator("#plan-result")).to_contain_text("in SE2")
    assert bodies[-1]["state_space"] == "SE2"
    assert bodies[-1]["start"] == [*START, -3.1416] and bodies[-1]["goal"] == [*GOAL, 0]
    assert bodies[-1]["seed"] == 4294967295
    assert "turning_radius" not in bodies[-1]
    # the grid planner searches positions only: it is not offered with a heading
    page.get_by_label("Motion model").select_option("R2")
    page.get_by_label("Planner").select_option("grid")
    page.get_by_label("Motion model").select_option("Dubins")
    expect(page.get_by_label("Planner")).to_have_value("RRTstar")
    expect(page.locator("#planner-note")).to_have_text(
        "The grid planner plans positions only, so the planner is now RRTstar.")
    assert page.locator('#planner option[value="grid"]').is_disabled()
    page.get_by_label("Motion model").select_option("R2")
    assert page.locator('#planner option[value="grid"]').is_enabled()
    assert len(bodies) == 2


def test_seeded_se2_plan_repeats(server: Server, page: Page) -> None:
    open_map(page, server.url, "hall")
    page.get_by_label("Motion model").select_option("SE2")
    type_poses(page, (*START, 0.5), (*GOAL, -1.0))
    # RRTConnect stops at its first solution, so the seeded run ends by its count, never the
    # clock, even on a busy machine (an optimizing planner's may not: see planning/query.py)
    page.get_by_label("Planner").select_option("RRTConnect")
    page.get_by_label("Time limit (s)").fill("5")
    page.get_by_label("Seed (optional)").fill("42")
    runs = []
    for _ in range(2):
        body = plan_and_wait(page)
        assert body["seed"] == 42 and body["state_space"] == "SE2"
        result = page.locator("#plan-result")
        assert result.get_attribute("data-state") == "path", result.inner_text()
        if page.locator("#path-details").get_attribute("open") is None:
            page.get_by_text("Path waypoints").click()  # open the list, as an operator would
        runs.append((page.locator("#path-list").inner_text(), re.sub(r"in \d+\.\d+ s", "", result.inner_text())))
    assert runs[0][0].count("heading") > 10
    assert runs[0] == runs[1]


def test_heading_arrows_point_where_the_heading_says(server: Server, page: Page) -> None:
    open_map(page, server.url, "hall")
    page.get_by_label("Show the last scan's beams").uncheck()
    type_poses(page, START, GOAL)
    east, north = (22, 0), (0, -22)  # canvas pixels from the marker: +x is right, +y is up (canvas y down)
    # R2: no heading, no arrow
    assert not dark_around(page, *START, *east) and not dark_around(page, *START, *north)
    page.get_by_label("Motion model").select_option("SE2")
    assert dark_around(page, *START, *east) and not dark_around(page, *START, *north)
    before = page.locator("#map-canvas").screenshot()
    page.locator("#start-theta").fill(str(math.pi / 2))
    assert dark_around(page, *START, *north) and not dark_around(page, *START, *east)
    assert page.locator("#map-canvas").screenshot() != before
    # the goal's arrow follows its own field: pi points to -x
    assert dark_around(page, *GOAL, *east)
    page.locator("#goal-theta").fill(str(math.pi))
    assert dark_around(page, *GOAL, -22, 0) and not dark_around(page, *GOAL, *east)
    expect(page.locator("#map-canvas")).to_have_attribute("aria-label", re.compile(
        r"start \(2\.525, 1\.525\), heading 1\.571 rad; goal \(7\.525, 1\.525\), heading 3\.142 rad"))
