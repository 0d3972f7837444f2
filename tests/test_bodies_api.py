"""POST /v1/bodies/fit and GET /v1/bodies/measurements through HTTP."""
from __future__ import annotations

PROBLEM = "application/problem+json"


def test_measurements_of_a_body_then_fit_back(client):
    r = client.get("/v1/bodies/measurements", params={"gender": 0.2, "weight": 0.7, "height": 0.6})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["phenotypes"]["gender"] == 0.2 and body["phenotypes"]["age"] == 0.8  # omitted: the default
    m = body["measurements"]
    assert 150 < m["height_cm"] < 220 and m["waist_cm"] < m["hips_cm"] and "ISO 8559-1" in body["standard"]
    ask = {k: m[k] for k in ("height_cm", "chest_cm", "waist_cm", "hips_cm", "inseam_cm")}
    r = client.post("/v1/bodies/fit", json=ask)
    assert r.status_code == 200, r.text
    fit = r.json()
    assert all(abs(v) <= fit["tolerance_cm"] for k, v in fit["residuals"].items() if k != "weight_kg")
    assert fit["residuals"]["weight_kg"] is None
    for k, v in ask.items():
        assert abs(fit["measurements"][k] - v) <= 1.0
    # the fitted phenotypes drape as they are
    r = client.get("/v1/bodies/measurements", params=fit["phenotypes"])
    assert r.status_code == 200 and abs(r.json()["measurements"]["chest_cm"] - ask["chest_cm"]) <= 1.0


def test_weight_and_gender(client):
    r = client.post("/v1/bodies/fit", json={"height_cm": 168, "chest_cm": 92, "waist_cm": 76, "hips_cm": 102, "inseam_cm": 78,
                                            "weight_kg": 63, "gender": "female"})
    assert r.status_code == 200, r.text
    fit = r.json()
    assert fit["phenotypes"]["gender"] >= 0.5
    assert abs(fit["residuals"]["weight_kg"]) <= fit["tolerance_kg"]


def test_impossible_combination_is_a_422_naming_the_measurement(client):
    r = client.post("/v1/bodies/fit", json={"height_cm": 180, "chest_cm": 60, "waist_cm": 150, "hips_cm": 100, "inseam_cm": 85})
    assert r.status_code == 422 and r.headers["content-type"].startswith(PROBLEM)
    pointers = {e["pointer"] for e in r.json()["errors"]}
    assert {"/chest_cm", "/waist_cm"} <= pointers
    assert "closest" in r.json()["errors"][0]["detail"]


def test_bad_requests(client):
    ok = {"height_cm": 180, "chest_cm": 100, "waist_cm": 85, "hips_cm": 100, "inseam_cm": 85}
    r = client.post("/v1/bodies/fit", json={**ok, "height_cm": 20})
    assert r.status_code == 422 and r.json()["errors"][0]["pointer"] == "/height_cm"
    r = client.post("/v1/bodies/fit", json={k: v for k, v in ok.items() if k != "inseam_cm"})
    assert r.status_code == 422 and r.json()["errors"][0]["pointer"] == "/inseam_cm"
    r = client.post("/v1/bodies/fit", json={**ok, "gender": "other"})
    assert r.status_code == 422 and r.json()["errors"][0]["pointer"] == "/gender"
    r = client.post("/v1/bodies/fit", content=b"height=180", headers={"content-type": "application/x-www-form-urlencoded"})
    assert r.status_code == 415
    r = client.get("/v1/bodies/measurements", params={"age": 0.3})
    assert r.status_code == 422 and r.json()["errors"][0]["parameter"] == "age"


def test_the_contract_examples_fit(client):
    examples = client.get("/openapi.json").json()["paths"]["/v1/bodies/fit"]["post"]["requestBody"]["content"]["application/json"]["examples"]
    for example in examples.values():
        r = client.post("/v1/bodies/fit", json=example["value"])
        assert r.status_code == 200, r.text
