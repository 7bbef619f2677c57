"""The web page in a real browser (headless Chromium, driven through its WebDriver) against a real
`dst serve`: a part uploaded with the page's own form, the job followed through its events to the
end, and the links the page then shows giving the job's mesh and report; a bad upload's error code
and message shown as the API gives them."""

from __future__ import annotations

import io
import shutil

import httpx
import numpy as np
import pytest
import trimesh

pytestmark = [pytest.mark.service, pytest.mark.slow]

webdriver = pytest.importorskip(
    "selenium.webdriver", reason="selenium is not installed (pip install selenium)"
)
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import WebDriverWait  # noqa: E402


@pytest.fixture
def browser():
    chromium, driver = shutil.which("chromium"), shutil.which("chromedriver")
    if chromium is None or driver is None:
        pytest.skip("Chromium and its WebDriver are not installed (apt-get install chromium chromium-driver)")
    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    # headless, and nothing that reaches for the network beyond the service (a closed machine)
    for arg in (
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-dev-shm-usage",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--no-first-run",
    ):
        options.add_argument(arg)
    b = webdriver.Chrome(options=options, service=webdriver.ChromeService(executable_path=driver))
    yield b
    b.quit()


def _fill(browser, name: str, value: str) -> None:
    field = browser.find_element(By.NAME, name)
    field.clear()
    field.send_keys(value)


def _status(browser) -> tuple[str, str]:
    el = browser.find_element(By.ID, "status")
    return el.text, el.get_attribute("class") or ""


def test_the_page_slices_an_uploaded_part_and_links_its_mesh_and_report(service_factory, browser, parts):
    svc = service_factory().start()
    browser.get(svc.url + "/")
    browser.find_element(By.NAME, "file").send_keys(str(parts["hemisphere"]))
    _fill(browser, "layer_height", "0.25")
    _fill(browser, "baselines", "occt_fast")
    browser.find_element(By.TAG_NAME, "button").click()

    WebDriverWait(browser, 240).until(lambda b: b.find_elements(By.CSS_SELECTOR, "#links a"))
    text, cls = _status(browser)
    assert text.startswith("succeeded") and cls != "err", text
    assert float(browser.find_element(By.ID, "bar").get_attribute("value")) == 1.0
    links = {a.text: a.get_attribute("href") for a in browser.find_elements(By.CSS_SELECTOR, "#links a")}
    assert set(links) == {"mesh (STL)", "mesh (3MF)", "report", "report JSON", "plot"}, links

    # the page's links are the job's: its job (the one the form made, with the form's values) ...
    (job,) = httpx.get(svc.url + "/v1/jobs").json()["jobs"]
    assert job["params"]["layer_height"] == 0.25 and links["mesh (STL)"].endswith(job["links"]["mesh"])
    # ... whose STL is a closed mesh of the 10 mm hemisphere with a ring of vertices on each of the
    # form's planes h0/2 + k h (h = 0.25 mm: 40 of them)
    mesh = trimesh.load(io.BytesIO(httpx.get(links["mesh (STL)"]).content), file_type="stl")
    assert mesh.is_watertight and len(mesh.faces) == job["result"]["triangles"]
    planes = 0.125 + 0.25 * np.arange(40)
    on = np.abs(mesh.vertices[:, 2, None] - planes[None, :]) < 1e-5
    assert (on.sum(axis=0) >= 3).all()
    # and whose report measures the DST mesh against the one baseline asked for, at those planes
    report = httpx.get(links["report JSON"]).json()
    assert [m["name"] for m in report["meshes"]] == ["dst", "occt_fast"]
    np.testing.assert_allclose(report["planes"], planes, atol=1e-9)
    assert len(report["meshes"][0]["layers"]) == len(planes)
    html = httpx.get(links["report"])
    assert html.status_code == 200 and "occt_fast" in html.text
    assert httpx.get(links["plot"]).text.lstrip().startswith(("<?xml", "<svg"))


def test_the_page_shows_why_an_upload_is_refused(service_factory, browser, parts, tmp_path):
    svc = service_factory().start()
    not_step = tmp_path / "notes.step"
    not_step.write_text("not a STEP file\n")
    browser.get(svc.url + "/")
    for path, field, value, code in (
        (not_step, None, None, "not_step"),
        (parts["hemisphere"], "layer_height", "5", "invalid_parameters"),
    ):
        browser.find_element(By.NAME, "file").send_keys(str(path))
        if field:
            _fill(browser, field, value)
        browser.find_element(By.TAG_NAME, "button").click()
        WebDriverWait(browser, 30).until(lambda b: _status(b)[1] == "err")
        text, _ = _status(browser)
        assert text.startswith(code + ": "), text
        browser.get(svc.url + "/")  # a fresh form
    # nothing was queued
    assert httpx.get(svc.url + "/v1/jobs").json()["jobs"] == []
