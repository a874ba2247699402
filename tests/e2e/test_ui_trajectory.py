"""The operator page's trajectory and rebuild panel in a real browser against a real server.

Same set-up as ``test_ui_browser.py``: a server process with a fresh data directory, the e2e world's hall scanned
into a map (each scan stamped, as a robot's are), Debian's Chromium driven by Playwright. What is checked is what an
operator relies on: the trajectory is drawn through the poses the scans were taken at (thinned when long, read again
only when the map changes), and the rebuild panel says how far a rebuild is, polls while it runs, and says why one
failed. Set UI_REBUILD_SCREENSHOT=/some/file.png to keep a screenshot of the page during a rebuild.
"""

from __future__ import annotations

import json
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
from playwright.sync_api import Page, Route, expect

from tests.e2e.conftest import PATIENCE_S, POSES, WORLD_MAP, Server, laser_json

pytestmark = pytest.mark.slow

# The hall (see test_ui_browser.py) with a 0.5 m margin all round.
ORIGIN = (-0.5, -0.5)
SIZE = (11.0, 7.0)
RES = WORLD_MAP["resolution"]
WIDTH, HEIGHT = round(SIZE[0] / RES), round(SIZE[1] / RES)
FIRST_STAMP_S = 1_700_000_000
#: More poses than the page draws one by one (it draws every k-th beyond about 5,000).
LONG = 6_000


def stamped(pose: tuple[float, float, float], k: int, **options: Any) -> dict[str, Any]:
    """The hall's scan from ``pose``, taken ``k`` seconds after the first."""
    return {**laser_json(pose, **options), "header": {"stamp": {"sec": FIRST_STAMP_S + k, "nanosec": 0}}}


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    srv = Server(tmp_path_factory.mktemp("ui-trajectory") / "data")
    try:
        srv.start()
        with httpx.Client(base_url=srv.url, timeout=60.0) as client:
            for name in ("hall", "long"):
                created = client.post("/maps", json={**WORLD_MAP, "name": name, "origin": list(ORIGIN),
                                                     "size": list(SIZE)})
                assert created.status_code == 201, created.text
            fused = client.post("/maps/hall/scans", json={"scans": [stamped(p, k) for k, p in enumerate(POSES)]})
            assert fused.status_code == 200, fused.text
            # a robot going round the hall's west room 6,000 times a scan, each scan of a few beams
            turns = np.linspace(0, 2 * np.pi, LONG, endpoint=False)
            way = [(2.5 + 1.5 * np.cos(a), 3.0 + 2.0 * np.sin(a), 0.0) for a in turns]
            for first in range(0, LONG, 250):
                batch = [stamped(p, first + k, beams=8) for k, p in enumerate(way[first:first + 250])]
                assert client.post("/maps/long/scans", json={"scans": batch}).status_code == 200
        yield srv
    finally:
        srv.stop()


def open_map(page: Page, url: str, name: str) -> None:
    page.goto(url + "/ui/")
    page.get_by_role("button", name=f"Show map {name}").click()
    expect(page.locator("#map-canvas")).to_have_attribute("data-version", re.compile(r"^\d+$"))
    page.get_by_label("Show the last scan's beams").uncheck()


#: For each world point, the canvas pixels in the trajectory's green within 2 pixels of where it is drawn.
_GREEN_NEAR = """([points, origin, res, w, h]) => {
    const c = document.getElementById('map-canvas');
    const g = c.getContext('2d');
    return points.map(([x, y]) => {
        const u = Math.round((x - origin[0]) / res / w * c.width);
        const v = Math.round((1 - (y - origin[1]) / res / h) * c.height);
        const d = g.getImageData(u - 2, v - 2, 5, 5).data;
        let n = 0;
        for (let i = 0; i < d.length; i += 4) if (d[i] < 60 && d[i + 1] > 120 && d[i + 2] < 120) n++;
        return n;
    });
}"""


def green_near(page: Page, points: list[tuple[float, float]]) -> list[int]:
    """``_GREEN_NEAR`` of the points, now."""
    return page.evaluate(_GREEN_NEAR, [points, list(ORIGIN), RES, WIDTH, HEIGHT])


def wait_for_green_at(page: Page, points: list[tuple[float, float]]) -> None:
    """Wait until the trajectory is drawn through every one of the points."""
    page.wait_for_function(f"(args) => ({_GREEN_NEAR})(args).every((n) => n > 0)",
                           arg=[points, list(ORIGIN), RES, WIDTH, HEIGHT], timeout=PATIENCE_S * 1000)


def polls_of_the_map_list(page: Page, count: int) -> None:
    """Wait until the page has polled the map list ``count`` more times (each poll ends before the next begins)."""
    for _ in range(count):
        with page.expect_request(lambda r: r.method == "GET" and urlsplit(r.url).path == "/maps",
                                 timeout=PATIENCE_S * 1000):
            pass


def test_the_trajectory_is_drawn_through_the_scans_poses_and_read_again_only_for_a_new_version(
        server: Server, page: Page) -> None:
    reads: list[str] = []
    page.on("request", lambda r: reads.append(r.url) if r.url.endswith("/trajectory") else None)
    open_map(page, server.url, "hall")
    text = page.locator("#trajectory-text")
    expect(text).to_have_text(f"Trajectory: {len(POSES)} poses, one per stored scan.")
    expect(page.locator("#map-canvas")).to_have_attribute("aria-label", re.compile(
        f"the trajectory of {len(POSES)} poses is drawn"))
    at_poses = [(x, y) for x, y, _ in POSES]
    assert all(n > 0 for n in green_near(page, at_poses))
    page.get_by_label("Show the trajectory").uncheck()
    assert green_near(page, at_poses) == [0] * len(POSES)
    page.get_by_label("Show the trajectory").check()

    polls_of_the_map_list(page, 3)
    assert len(reads) == 1  # the map did not change: not read again
    with httpx.Client(base_url=server.url, timeout=60.0) as client:
        pose = (8.0, 1.0, 0.0)  # a new scan in the east room's corner: the trajectory goes on to it
        assert client.post("/maps/hall/scans", json={"scans": [stamped(pose, len(POSES))]}).status_code == 200
    expect(text).to_have_text(f"Trajectory: {len(POSES) + 1} poses, one per stored scan.")
    assert len(reads) == 2
    assert green_near(page, [pose[:2]])[0] > 0


def test_a_long_trajectory_is_drawn_thinned(server: Server, page: Page) -> None:
    open_map(page, server.url, "long")
    expect(page.locator("#trajectory-text")).to_have_text(f"Trajectory: {LONG:,} poses, every 2nd drawn, one per "
                                                          "stored scan.")
    # the loop is drawn all round: every 500th pose of it lies on the line
    turns = np.linspace(0, 2 * np.pi, LONG, endpoint=False)[::500]
    assert all(n > 0 for n in green_near(page, [(2.5 + 1.5 * np.cos(a), 3.0 + 2.0 * np.sin(a)) for a in turns]))


def _status(state: str, done: int, **fields: Any) -> dict[str, Any]:
    return {"state": state, "id": "5eed", "requested": "2026-12-07T13:00:00+00:00", "from_version": 1,
            "scans_reposed": 27, "scans_done": done, "scans_total": 100, "elapsed_s": done / 10, "eta_s": 6.0,
            "version": None, "error": None, **fields}


def test_the_rebuild_panel_shows_the_progress_while_it_runs_and_why_it_failed(
        server: Server, page: Page, tmp_path: Path) -> None:
    # the service's answers, one a read, as a rebuild goes: the page shows each as it comes
    answers = [_status("running", 40), _status("running", 80),
               _status("failed", 90, error="the map's stored batch 3 is corrupt", eta_s=None)]
    reads: list[int] = []

    def rebuild(route: Route) -> None:
        reads.append(len(reads))
        answer = answers[min(len(reads), len(answers)) - 1]
        route.fulfill(status=200, content_type="application/json", body=json.dumps(answer))

    page.route("**/maps/hall/rebuild", rebuild)
    open_map(page, server.url, "hall")
    panel, bar = page.locator("#rebuild"), page.locator("#rebuild-bar")
    expect(panel).to_have_attribute("data-state", "running")
    expect(page.locator("#rebuild-state")).to_contain_text("Rebuilding on the corrected trajectory of")
    expect(page.locator("#rebuild-figures")).to_contain_text("40 of 100 scans re-fused, 4.0 s elapsed, 6.0 s left; "
                                                             "27 scans re-posed (of version 1)")
    assert bar.evaluate("b => [b.max, b.value]") == [100, 40]
    shot = tmp_path / "ui_rebuild.png"
    page.screenshot(path=str(shot), full_page=True)
    if os.environ.get("UI_REBUILD_SCREENSHOT"):
        shutil.copyfile(shot, os.environ["UI_REBUILD_SCREENSHOT"])
    # it is read again at every poll while it runs, without a reload
    expect(page.locator("#rebuild-figures")).to_contain_text("80 of 100 scans re-fused")
    assert bar.evaluate("b => b.value") == 80
    expect(panel).to_have_attribute("data-state", "failed")
    expect(page.locator("#rebuild-error")).to_have_text("Why: the map's stored batch 3 is corrupt")
    expect(page.locator("#rebuild-state")).to_contain_text("failed; the map is as it was")
    expect(bar).to_be_hidden()
    # once it has ended, no longer at every poll
    count = len(reads)
    polls_of_the_map_list(page, 2)
    assert len(reads) == count


def test_a_corrected_trajectory_put_by_a_slam_node_shows_as_rebuilt_with_the_new_poses(
        server: Server, page: Page) -> None:
    with httpx.Client(base_url=server.url, timeout=60.0) as client:
        created = client.post("/maps", json={**WORLD_MAP, "name": "moved", "origin": list(ORIGIN), "size": list(SIZE)})
        assert created.status_code == 201, created.text
        fused = client.post("/maps/moved/scans", json={"scans": [stamped(p, k) for k, p in enumerate(POSES)]})
        assert fused.status_code == 200, fused.text
        open_map(page, server.url, "moved")
        expect(page.locator("#rebuild")).to_have_attribute("data-state", "none")
        expect(page.locator("#rebuild-state")).to_have_text("No corrected trajectory yet.")
        # the loop closure: every pose was 0.3 m further north than the robot thought
        path = client.get("/maps/moved/trajectory").json()
        for pose in path["poses"]:
            pose["pose"]["position"]["y"] += 0.3
        put = client.put("/maps/moved/trajectory", json={"header": path["header"], "poses": path["poses"]})
        assert put.status_code == 202, put.text
    expect(page.locator("#rebuild")).to_have_attribute("data-state", "done")
    expect(page.locator("#rebuild-state")).to_contain_text(re.compile(r"Rebuilt on the corrected trajectory of "
                                                                      r"\d\d:\d\d:\d\d: map version 2\."))
    expect(page.locator("#rebuild-figures")).to_contain_text(f"{len(POSES)} scans re-posed; {len(POSES)} scans "
                                                             "re-fused in")
    expect(page.locator("#rebuild-bar")).to_be_hidden()
    # the map and its trajectory are read again: the line now runs through the corrected poses
    expect(page.locator("#map-canvas")).to_have_attribute("data-version", "2")
    wait_for_green_at(page, [(x, y + 0.3) for x, y, _ in POSES])
