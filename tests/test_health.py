import time

from fastapi.testclient import TestClient

from app.config import Settings
from app.api.factory import create_app


def test_health_answers_ok() -> None:
    client = TestClient(create_app())
    response = client.get("/health")
    assert response.status_code == 200
    assert response.json() == {"status": "ok"}


def test_health_and_ready_answer_head_as_get_without_a_body(tmp_path) -> None:
    # load balancers and `curl -I` probe with HEAD (it was 405)
    with TestClient(create_app(Settings(data_dir=tmp_path, plan_warmup=False, plan_workers=1))) as client:
        head, get = client.head("/health"), client.get("/health")
        assert head.status_code == get.status_code == 200 and head.content == b""
        # readiness flips once the plan worker is up: compare the two once it has
        deadline = time.monotonic() + 120
        while client.get("/ready").status_code != 200 and time.monotonic() < deadline:
            time.sleep(0.05)
        ready_head, ready_get = client.head("/ready"), client.get("/ready")
        assert ready_head.status_code == ready_get.status_code == 200 and ready_head.content == b""
