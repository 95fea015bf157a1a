"""A live `--teacher human` run, labelled by a scripted browser: the issue's "a person starts
a cheetah_run PRIOR run, answers its first round in a browser and watches it continue".

    python -m benchmarks.runs.labelling_live_run   (needs Debian's chromium and chromium-driver)

`hprior train --task cheetah_run --algo prior --preset smoke --teacher human` runs in a child
process. When it prints round 1's address, headless Chromium (Selenium) opens the page, waits
until both clips play (screenshot: benchmarks/results/runs/labelling_human_run.png), and answers
the whole round as the oracle would, one key press per query (1 left, 2 right) after each
query's clips play; later rounds are answered through HTTP. The run goes on to the end; the
last line says how the answers were given and when each round was asked.
"""
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

SCREENSHOT = Path(__file__).resolve().parents[1] / "results" / "runs" / "labelling_human_run.png"
FIRST_ROUND = 10  # the smoke preset's queries per round, one seed (12345)


def main() -> None:
    out = Path(tempfile.mkdtemp()) / "run"
    t0 = time.time()
    proc = subprocess.Popen(
        [sys.executable, "-m", "hprior_jax.cli", "train", "--task", "cheetah_run", "--algo",
         "prior", "--preset", "smoke", "--teacher", "human", "--label-port", "8777",
         "--out", str(out), "--no-progress"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)

    def oracle_says_right(qid):
        with np.load(out / "labels" / "segments" / f"{qid}.npz") as z:
            return z["true_reward2"].sum() > z["true_reward1"].sum()

    rounds, by_browser, by_http = [], 0, 0
    for line in proc.stdout:
        sys.stdout.write(f"[{time.time() - t0:6.1f}s] {line}")
        sys.stdout.flush()
        m = re.search(r"open (http://\S+)", line)
        if not m:
            continue
        url = m.group(1).rstrip("/")
        rounds.append(time.time() - t0)
        if len(rounds) == 1:
            by_browser = answer_in_browser(url, oracle_says_right)
            continue
        while True:
            q = httpx.get(url + "/api/next", timeout=10).json()["query"]
            if q is None:
                break
            answer = "right" if oracle_says_right(q["id"]) else "left"
            r = httpx.post(url + "/api/answer", timeout=10,
                           json={"id": q["id"], "answer": answer, "labeller": "script"})
            assert r.status_code == 200, r.text
            by_http += 1
    proc.wait()
    print(f"exit {proc.returncode}; {by_browser} answers by key in the browser, {by_http} by "
          f"HTTP; rounds asked at {[round(r) for r in rounds]} s; wall {time.time() - t0:.0f} s;"
          f" run directory {out}")


def answer_in_browser(url: str, oracle_says_right) -> int:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By

    options = webdriver.ChromeOptions()
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                "--autoplay-policy=no-user-gesture-required", "--window-size=1000,720"):
        options.add_argument(arg)
    d = webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=options)
    d.get(url + "/")
    playing = lambda v: d.execute_script(
        f"const v = document.getElementById('{v}');"
        "return v.readyState >= 2 && !v.paused && v.currentTime > 0;")
    for i in range(FIRST_ROUND):
        qid = f"r1-s12345-q{i:04d}"
        wait(lambda: qid in d.find_element(By.ID, "where").text)
        wait(lambda: playing("left") and playing("right"))
        if i == 0:
            time.sleep(1.0)
            d.save_screenshot(str(SCREENSHOT))
        d.find_element(By.TAG_NAME, "body").send_keys("2" if oracle_says_right(qid) else "1")
    wait(lambda: f"{FIRST_ROUND} of {FIRST_ROUND}" in d.find_element(By.ID, "progress").text)
    d.quit()
    return FIRST_ROUND


def wait(predicate, timeout=120):
    end = time.time() + timeout
    while time.time() < end:
        if predicate():
            return
        time.sleep(0.1)
    raise TimeoutError("the page did not get there in time")


if __name__ == "__main__":
    main()
