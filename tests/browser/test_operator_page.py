"""The operator page in headless Chromium (the OS package) against `dpmhw session start --mock`.

Skipped where /usr/bin/chromium or chromedriver is missing, except under CI (CI=true), where
`.ci/run` installs them and a missing browser is a failure.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import threading
import urllib.request

import pytest

from dpmhw.session.testing import wait_for

pytestmark = pytest.mark.browser

CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", shutil.which("chromedriver") or "/usr/bin/chromedriver"
TOKEN = "browser-test-token"

if not (os.path.exists(CHROMIUM) and os.path.exists(CHROMEDRIVER)):
    if os.environ.get("CI"):
        pytest.fail("CI needs /usr/bin/chromium and chromedriver (apt-get install chromium chromium-driver)", pytrace=False)
    pytest.skip("no /usr/bin/chromium + chromedriver (apt-get install chromium chromium-driver)", allow_module_level=True)

webdriver = pytest.importorskip("selenium.webdriver")
from selenium.common.exceptions import StaleElementReferenceException  # noqa: E402
from selenium.webdriver.chrome.service import Service  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.common.keys import Keys  # noqa: E402

WAIT_S = 30  # for what must happen eventually: generous, as only broken code waits this long


@pytest.fixture(scope="module")
def session():
    """(API URL, the start command's output lines so far) of a `session start --mock`."""
    # api.priority=low: a SCHED_IDLE API process gets next to no CPU beside a CPU hog; a generous
    # tracking stale limit and watchdog: on a loaded machine the loop is late by far more than the
    # defaults allow (and a loop that presents late is killed as hung), which these tests do not test
    args = ["session", "start", "--mock", "--status-every", "0", "--port", "0",
            "--set", "render.width=64", "--set", "render.height=48", "--set", "api.priority=low",
            "--set", "safety.stale_after_ms=1000", "--set", "safety.watchdog_s=5"]
    proc = subprocess.Popen([sys.executable, "-c", "from dpmhw.cli import main; main()", *args],
                            env={**os.environ, "DPMHW_API_TOKEN": TOKEN},
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    try:
        # ready when it says so, however long a first compile takes; a start that ends is a failure
        if not wait_for(lambda: any("API on http://" in line for line in lines) or proc.poll() is not None, 900):
            pytest.fail("session did not start:\n" + "".join(lines))
        if proc.poll() is not None:
            pytest.fail(f"session exited with {proc.returncode} before its API was up:\n" + "".join(lines))
        url = next(m.group(1) for line in lines if (m := re.search(r"API on (http://\S+)", line)))
        if not wait_for(lambda: _get(url, "/status").get("state") == "running", 60):
            pytest.fail(f"session never ran: {_get(url, '/status')}")
        yield url, lines
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)
        reader.join(timeout=10)
        proc.stdout.close()


@pytest.fixture(scope="module")
def session_url(session):
    return session[0]


def _get(url: str, path: str) -> dict:
    with urllib.request.urlopen(url + path, timeout=WAIT_S) as r:  # an API process starved beside a hog answers late
        return json.loads(r.read())


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run", "--window-size=1280,1000",
                 f"--user-data-dir={tmp_path_factory.mktemp('chromium-profile')}"):
        opts.add_argument(flag)
    driver = webdriver.Chrome(options=opts, service=Service(CHROMEDRIVER))
    driver.set_page_load_timeout(30)
    yield driver
    driver.quit()


@pytest.fixture
def page(browser, session_url):
    browser.get(session_url + "/")
    browser.execute_script("sessionStorage.clear()")
    browser.refresh()
    assert wait_for(lambda: browser.find_elements(By.ID, "set-alpha"), WAIT_S), "controls were not built from /settings"
    return browser


def _text(driver, element_id: str) -> str:
    return _css_text(driver, "#" + element_id)


def _css_text(driver, selector: str) -> str:
    """Text of the matching elements; the page redraws parts of itself, so a stale read is retried."""
    for _ in range(10):
        try:
            return " ".join(e.text for e in driver.find_elements(By.CSS_SELECTOR, selector))
        except StaleElementReferenceException:
            continue
    return ""


def _enter_token(driver) -> None:
    driver.find_element(By.ID, "token").send_keys(TOKEN, Keys.ENTER)
    assert wait_for(lambda: "token set" in _text(driver, "token-state"), WAIT_S)


def test_live_frame_updates_and_state_is_in_words(page, tmp_path):
    img = page.find_element(By.ID, "frame")
    assert wait_for(lambda: img.get_attribute("data-frame-number"), WAIT_S)
    first = int(img.get_attribute("data-frame-number"))
    assert wait_for(lambda: int(img.get_attribute("data-frame-number") or 0) > first, WAIT_S), "the frame never changed"
    assert wait_for(lambda: page.execute_script("return arguments[0].naturalWidth", img) == 64, WAIT_S)
    # the caption gives the output size, what /frame.png is, and the shading size beside it
    assert wait_for(lambda: "64×48 output (shaded at 16×12)" in _text(page, "frame-info"), WAIT_S), _text(page, "frame-info")
    assert wait_for(lambda: _text(page, "state") == "Projecting", WAIT_S), _text(page, "state")  # tracking may lag under load
    assert wait_for(lambda: page.find_elements(By.CSS_SELECTOR, "#stages tbody tr"), WAIT_S)
    assert "render" in _text(page, "stages") and "streaming" in _text(page, "devices")
    assert wait_for(lambda: "rate hz" in _text(page, "devices"), WAIT_S)  # computed from the tracker's frame count
    # what the quality governor chose and why, in words (its rung, its target and the display it came from)
    assert wait_for(lambda: all(w in _text(page, "governor") for w in ("target fps", "the display's refresh", "why", "chose")),
                    WAIT_S), _text(page, "governor")
    page.save_screenshot(str(tmp_path / "operator-page.png"))
    assert (tmp_path / "operator-page.png").stat().st_size > 10_000


def test_alpha_slider_changes_the_live_setting(page, session_url, tmp_path):
    _enter_token(page)
    before = _get(session_url, "/settings")["alpha"]
    slider = page.find_element(By.ID, "set-alpha")
    slider.send_keys(Keys.END)  # the slider's maximum: 1.0
    assert wait_for(lambda: _get(session_url, "/settings")["alpha"] == 1.0, WAIT_S), _text(page, "message")
    assert wait_for(lambda: "alpha = 1 accepted" in _text(page, "message"), WAIT_S), _text(page, "message")
    slider.send_keys(Keys.HOME)
    assert wait_for(lambda: _get(session_url, "/settings")["alpha"] == pytest.approx(0.01), WAIT_S), _text(page, "message")
    page.find_element(By.ID, "set-reuse_mode").send_keys("same-pixel")
    assert wait_for(lambda: _get(session_url, "/settings")["reuse_mode"] == "same-pixel", WAIT_S), _text(page, "message")
    assert before != 0.01
    page.save_screenshot(str(tmp_path / "after-alpha.png"))


def test_rejections_show_the_api_reason(page, session_url):
    page.find_element(By.ID, "blank").click()  # no token entered in this browser session
    assert wait_for(lambda: "rejected (401)" in _text(page, "message"), WAIT_S)
    assert "bearer token" in _text(page, "message")
    assert "operator" not in [c["name"] for c in _get(session_url, "/status")["causes"]]
    _enter_token(page)
    spp = page.find_element(By.ID, "set-spp")
    spp.clear()
    spp.send_keys("65", Keys.TAB)  # above the API's bound: refused with its reason
    assert wait_for(lambda: "rejected (422)" in _text(page, "message"), WAIT_S)
    assert "spp" in _text(page, "message") and "64" in _text(page, "message")
    assert _get(session_url, "/settings")["spp"] == 1


def test_blank_then_resume_from_the_page(page, session_url, tmp_path):
    """The page's blank goes through the operator port (a cross-origin request the port allows
    the page alone), resume and reset through the service."""
    _enter_token(page)
    operator_blanks = lambda: _get(session_url, "/status")["api"]["operator"]["blanks"]  # noqa: E731
    assert wait_for(lambda: "operator port first" in _text(page, "operator-port"), WAIT_S)
    before = operator_blanks()
    page.find_element(By.ID, "blank").click()
    assert wait_for(lambda: _text(page, "state") == "Dark: operator blank", WAIT_S), _text(page, "state")
    assert _get(session_url, "/status")["state"] == "blanked"
    assert wait_for(lambda: operator_blanks() == before + 1, WAIT_S), _get(session_url, "/status")["api"]
    assert wait_for(lambda: "operator" in _text(page, "causes"), WAIT_S), _text(page, "causes")  # beside any tracking cause on a loaded machine
    img = page.find_element(By.ID, "frame")
    assert wait_for(lambda: img.get_attribute("data-blank") == "true", WAIT_S)
    page.save_screenshot(str(tmp_path / "blanked.png"))
    page.find_element(By.ID, "resume").click()
    assert wait_for(lambda: _get(session_url, "/status")["state"] == "running", WAIT_S)
    assert wait_for(lambda: _text(page, "state") == "Projecting", WAIT_S)
    page.find_element(By.ID, "reset-history").click()
    assert wait_for(lambda: "history reset" in _text(page, "message"), WAIT_S)


def test_docs_and_redoc_render_from_local_assets(browser, session_url):
    browser.get(session_url + "/docs")
    assert wait_for(lambda: "dpmhw session" in _css_text(browser, ".swagger-ui .info"), WAIT_S)
    assert browser.find_elements(By.CSS_SELECTOR, ".opblock"), "Swagger UI drew no operations"
    browser.get(session_url + "/redoc")
    assert wait_for(lambda: "PATCH" in _css_text(browser, "body").upper() and "settings" in _css_text(browser, "body"), 30)
    urls = browser.execute_script("return performance.getEntriesByType('resource').map(e => e.name)")
    # ReDoc's "API docs by Redocly" footer badge is the one remote image; it hides itself offline.
    remote = [u for u in urls if not u.startswith((session_url, "data:", "blob:"))]
    assert urls and remote in ([], ["https://cdn.redoc.ly/redoc/logo-mini.svg"]), urls


def test_start_up_output_gives_the_operator_page_address(session):
    url, lines = session
    assert any(line.strip() == f"operator page: {url}/ (it says why while the session is not up yet)"
               for line in lines), "".join(lines)


def test_the_start_output_and_the_page_give_the_operator_port(session, page):
    url, lines = session
    operator = _get(url, "/status")["api"]["operator"]["url"]
    assert operator != url and any(line.startswith("operator port") and line.strip().endswith(operator)
                                   for line in lines), "".join(lines)
    assert _get(operator, "/status")["state"] == _get(url, "/status")["state"]
    assert wait_for(lambda: f"operator port first ({operator})" in _text(page, "operator-port"), WAIT_S)


def test_a_hold_off_an_operator_blank_and_lost_tracking_are_told_apart(page):
    """The page's words for statuses made by the session's own safety monitor (fake clock)."""
    from dpmhw.session.safety import SafetyMonitor

    now = [0]
    safety = SafetyMonitor(holdoff_s=2.0, clock=lambda: now[0])
    safety.mark_started()

    def words() -> str:
        view = safety.view()
        st = {"state": view.state.value, "reason": view.reason, "output_on": view.output_on,
              "causes": [{"name": c.name, "kind": c.kind, "reason": c.reason} for c in view.causes]}
        return page.execute_script("return stateWords(arguments[0])", st)

    assert words() == "Projecting"
    safety.update("tracking", True, "rigid body 1: no sample yet (tracker lost)")
    assert words() == "Dark: tracking lost"
    now[0] += 10**9
    safety.update("tracking", False)
    assert safety.view().state.value == "blanked"
    assert words() == "Dark: tracking hold-off (resumes by itself)"
    safety.operator_blank()
    assert words() == "Dark: operator blank"
    safety.request_resume()
    assert words() == "Dark: hold-off (resumes by itself)"
    now[0] += 3 * 10**9
    assert words() == "Projecting"
    manual = SafetyMonitor(holdoff_s=0.0, resume="manual", clock=lambda: now[0])
    manual.mark_started()
    manual.update("tracking", True, "lost")
    manual.update("tracking", False)
    view = manual.view()
    st = {"state": view.state.value, "reason": view.reason, "causes": []}
    assert page.execute_script("return stateWords(arguments[0])", st) == "Dark: waiting for resume"
