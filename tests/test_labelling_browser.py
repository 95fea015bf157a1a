"""The labelling page in a real browser: headless Chromium (Debian's `chromium` and
`chromium-driver`, installed by .ci/setup) driven by Selenium loads the page served by uvicorn,
sees both clips play, the goal line, the speed and step controls, answers that wait until
both clips have played through, answers with a click and with a key, reloads and finds its
progress.
The screenshot lands in the test's temporary folder (tests write nothing else); no copy is
tracked (benchmarks/results/runs/labelling_human_run.png shows the page in a live run)."""
import shutil
import time

import numpy as np
import pytest

from tests.test_labelling import folder  # noqa: F401  (the fixture: three cheetah queries)

CHROMEDRIVER = shutil.which("chromedriver")


@pytest.fixture()
def server(folder):  # noqa: F811
    from hprior_jax.labelling.server import BackgroundServer, ServerOptions

    srv = BackgroundServer(folder, ServerOptions(port=0))
    yield srv.url, folder
    srv.close()


@pytest.fixture()
def browser():
    if CHROMEDRIVER is None:
        pytest.fail("chromedriver not found: apt-get install chromium chromium-driver "
                    "(bash .ci/setup does)")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                "--autoplay-policy=no-user-gesture-required", "--window-size=1000,720"):
        options.add_argument(arg)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    yield driver
    driver.quit()


def _wait(predicate, timeout=20.0):
    end = time.time() + timeout
    while time.time() < end:
        value = predicate()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError("timed out")


def _playing(driver, vid):
    return driver.execute_script(
        f"const v = document.getElementById('{vid}');"
        "return v.readyState >= 2 && !v.paused && v.currentTime > 0 && v.videoWidth > 0;")


def test_a_person_labels_in_a_browser(server, browser, tmp_path):
    from selenium.webdriver.common.by import By

    url, folder = server
    browser.get(url)
    _wait(lambda: "r1-q0000" in browser.find_element(By.ID, "where").text)
    _wait(lambda: _playing(browser, "left") and _playing(browser, "right"))
    assert "0 of 3 answered" in browser.find_element(By.ID, "progress").text
    assert browser.find_element(By.ID, "goal").text == (
        "Goal: Run forward (to the right) as fast as possible.")
    script = browser.execute_script
    right_button = browser.find_element(By.CSS_SELECTOR, "[data-answer=right]")
    _wait(right_button.is_enabled)  # both clips played through once
    assert browser.save_screenshot(str(tmp_path / "labelling_page.png"))
    assert (tmp_path / "labelling_page.png").stat().st_size > 1000
    # speed and step control both clips together
    browser.find_element(By.CSS_SELECTOR, "#speed option[value='0.25']").click()
    assert script("return [left.playbackRate, right.playbackRate]") == [0.25, 0.25]
    browser.find_element(By.ID, "forward").click()
    assert script("return left.paused && right.paused && left.currentTime === right.currentTime")
    browser.find_element(By.ID, "pause").click()  # plays again
    _wait(lambda: _playing(browser, "left") and _playing(browser, "right"))
    # not yet seen: no answer is taken, by button or key
    script("seen = {left: false, right: false}; gate();")
    assert not right_button.is_enabled()
    browser.find_element(By.TAG_NAME, "body").send_keys("2")
    time.sleep(0.3)
    assert folder.answers() == {} and "r1-q0000" in browser.find_element(By.ID, "where").text
    _wait(right_button.is_enabled)  # the loops wrap: seen again
    # a click, then a key
    right_button.click()
    _wait(lambda: "r1-q0001" in browser.find_element(By.ID, "where").text)
    _wait(browser.find_element(By.CSS_SELECTOR, "[data-answer=left]").is_enabled)
    browser.find_element(By.TAG_NAME, "body").send_keys("1")
    _wait(lambda: "r1-q0002" in browser.find_element(By.ID, "where").text)
    answers = folder.answers()
    assert {k: v["answer"] for k, v in answers.items()} == {"r1-q0000": "right",
                                                            "r1-q0001": "left"}
    # a reload resumes where the labelling stopped
    browser.refresh()
    _wait(lambda: "2 of 3 answered" in browser.find_element(By.ID, "progress").text)
    assert "r1-q0002" in browser.find_element(By.ID, "where").text


@pytest.fixture()
def drawer_server(tmp_path):
    """Two drawer_open segments (the drawer closed / pulled out) as a query folder."""
    import mujoco

    import tasks
    from hprior_jax.labelling.server import BackgroundServer, ServerOptions
    from hprior_jax.labelling.store import QueryFolder, write_queries

    model = tasks.make("drawer_open").mj_model
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    slide = model.jnt_qposadr[model.joint("goal_slidey").id]

    def segment(pull: float, steps: int = 4) -> dict:
        qpos = np.repeat(data.qpos[None], steps, axis=0)
        qpos[:, slide] = np.linspace(0, pull, steps)
        return {"qpos": qpos, "qvel": np.zeros((steps, model.nv)),
                "mocap_pos": np.repeat(data.mocap_pos[None], steps, axis=0),
                "mocap_quat": np.repeat(data.mocap_quat[None], steps, axis=0)}

    write_queries(tmp_path / "q", "drawer_open", 1, [(segment(-0.15), segment(0.0))], fps=20.0)
    folder = QueryFolder(tmp_path / "q")
    srv = BackgroundServer(folder, ServerOptions(port=0))
    yield srv.url, folder
    srv.close()


def test_a_person_labels_a_metaworld_pair(drawer_server, browser):
    from selenium.webdriver.common.by import By

    url, folder = drawer_server
    browser.get(url)
    _wait(lambda: "drawer_open" in browser.find_element(By.ID, "where").text)
    assert browser.find_element(By.ID, "goal").text == "Goal: Pull the drawer open."
    _wait(lambda: _playing(browser, "left") and _playing(browser, "right"))
    left_button = browser.find_element(By.CSS_SELECTOR, "[data-answer=left]")
    _wait(left_button.is_enabled)
    left_button.click()
    _wait(lambda: folder.answers())
    assert folder.answers()["r1-q0000"]["answer"] == "left"
